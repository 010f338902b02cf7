"""Params: the schema (typed sections), composition of profiles into params.yaml, loading and fingerprints,
the params -> library casts (build), the torch device set-up (device), `--help` text."""
