"""Typer apps only: parse -> call core -> render output. No cloud SDK imports here."""
