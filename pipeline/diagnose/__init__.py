"""Mismatch diagnosis: locate where a recording departs from its passport, name, model, refit."""
