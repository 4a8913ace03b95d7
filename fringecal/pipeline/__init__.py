"""Steps of ``fringecal run`` that have no home elsewhere: simulated prior calibrations,
extraction over measurement stores, start values, simulated ball-bar verification."""
