"""Tests driving the dashboard in a real Chromium."""
