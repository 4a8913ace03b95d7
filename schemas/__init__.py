"""Table contracts (pandera) shared by fringecal, tasks and flows."""

from .tables import (  # noqa: F401
    FREE_COLUMNS,
    REJECTION_REASONS,
    ArtefactTable,
    ControlPointsTable,
    LabelOutcomesTable,
    PointsTable,
    PosePlanTable,
    PosesTable,
    RodsTable,
    ScannerLinksTable,
    SensorParametersTable,
    SphereFitsTable,
    SphereCentresTable,
    TableError,
    ThermalLogTable,
    read_csv_text,
    read_table,
    validate_table,
    write_table,
)
