"""Tests of the wire contract: the bake settings as a user reads them."""
