"""Params: the schema, composition of profiles into params.yaml, loading, `--help` text."""
