"""Tests of texelbake.render."""
