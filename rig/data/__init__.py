"""Data shipped with the package: the default simulated rig (``default_rig.toml``) and the config's JSON schema."""
from __future__ import annotations

from importlib import resources

DEFAULT_RIG = "default_rig.toml"


def default_config_text() -> str:
    """The text of the default simulated rig's TOML config (``rig/data/default_rig.toml``)."""
    return resources.files("rig.data").joinpath(DEFAULT_RIG).read_text()
