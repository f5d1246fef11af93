"""Presets: one per dataset kind and a demo. Each module exposes ``get_config() -> SLAMConfig``."""
