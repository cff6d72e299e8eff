"""Tests of texelbake.cpm.avis."""
