"""Replica (NICE-SLAM renders, 1200x680, exact depth): paper settings R = 10, K_c = 10."""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="replica", data=DataConfig(layout="auto"), track=TrackConfig(stride=10, k=10))
