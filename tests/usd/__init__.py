"""Tests of what we write as USD: LOD export, skinned LODs, interop."""
