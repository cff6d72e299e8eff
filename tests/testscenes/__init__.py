"""Tests of texelbake.testscenes (the generated test scenes)."""
