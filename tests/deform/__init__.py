"""Tests of texelbake.deform."""
