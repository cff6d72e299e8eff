"""Tests of texelbake.srf."""
