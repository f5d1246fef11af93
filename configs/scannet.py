"""ScanNet (640x480 depth): paper settings R = 5, K_c = 15; a larger geometry set for its long scenes."""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="scannet", data=DataConfig(layout="auto"), track=TrackConfig(stride=5, k=15, capacity=1 << 20, plane_points=True, depth_weight_power=2.0))
