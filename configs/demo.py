"""The built-in synthetic room (no download): the default of `sgad-jax run`."""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(
        name="demo",
        data=DataConfig(path="", layout="synthetic"),
        track=TrackConfig(stride=4, k=15),
    )
