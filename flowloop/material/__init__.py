"""Material profiles: the schema and its lines, ddPrint's format, plots."""
