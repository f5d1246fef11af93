"""TUM RGB-D (640x480, Kinect v1): paper settings R = 5, K_c = 23."""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="tum", data=DataConfig(layout="auto"), track=TrackConfig(stride=5, k=23, plane_points=True, depth_weight_power=2.0))
