"""Tests of texelbake.scene (the USD ingest)."""
