"""Recorded traces: the schema, readers and writers, unit mapping, validation, channel metrics."""
