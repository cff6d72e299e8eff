"""Tests of texelbake.scenes (the generated test scenes)."""
