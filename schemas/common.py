"""Small wire models shared by every resource."""

from __future__ import annotations

from pydantic import BaseModel


class Message(BaseModel):
    message: str


class HealthCheck(BaseModel):
    status: str
    database: bool
    broker: bool
    version: str
