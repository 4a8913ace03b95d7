"""Table contracts (pandera) shared by fringecal, tasks and flows."""

from .tables import (  # noqa: F401
    FREE_COLUMNS,
    ArtefactTable,
    CalibratedPosesTable,
    CalibratedSensorsTable,
    ControlPointsTable,
    MeasurementResidualsTable,
    PosePlanTable,
    PosesTable,
    RodsTable,
    SensorParametersTable,
    SphereCentresTable,
    SphereResidualsTable,
    TableError,
    ThermalLogTable,
    read_csv_text,
    read_table,
    validate_table,
    write_table,
)
