"""The built-in synthetic room (no download): the default of `sgad-jax run`."""

from sgad_jax.config import DataConfig, MapConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(
        name="demo",
        data=DataConfig(path="", layout="synthetic"),
        track=TrackConfig(stride=4, k=15),
        map=MapConfig(iterations=30),  # a quick first run; the dataset presets use 40 (the paper's 100)
    )
