"""What a run leaves: the record and telemetry, JUnit, reports, plots, exports, the Rerun view."""
