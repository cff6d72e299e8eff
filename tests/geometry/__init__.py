"""Tests of texelbake.geometry."""
