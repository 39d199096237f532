"""Files a calibration reads and writes: ``dataset`` the dataset directory and its
manifest (the one file format calib owns); ``metafile`` PLUS sequence files
(``.mha``/``.mhd``); ``plus_import`` PLUS recordings as datasets; ``plus_config`` PLUS's
device-set XML (phantom definition, coordinate definitions)."""
