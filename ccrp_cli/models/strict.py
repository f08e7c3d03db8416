"""The base of every model read from a user's file: unknown keys are errors, not ignored."""

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")
