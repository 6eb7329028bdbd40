"""pytest plugin: the `drivebench` fixture (being written)."""
