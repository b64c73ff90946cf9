"""Prompt templates (``*.txt``), read by ``ppprops.wire.prompt.template``."""
