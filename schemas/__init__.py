"""Pydantic models of the wire contract (bake settings, jobs, reports). No heavy imports here."""
