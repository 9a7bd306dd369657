"""The plugin host: hook specifications, plugin lifecycle with deadlines, terminal ownership."""
