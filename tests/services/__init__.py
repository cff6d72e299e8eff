"""Tests of the API (services/), in process and against real processes."""
