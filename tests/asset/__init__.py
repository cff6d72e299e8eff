"""Tests of texelbake.asset (the USD ingest)."""
