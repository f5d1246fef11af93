"""7-Scenes (640x480 Kinect v1, KinectFusion ground truth): the ScanNet-like settings R = 5, K_c = 15."""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="7scenes", data=DataConfig(layout="auto"), track=TrackConfig(stride=5, k=15, plane_points=True, depth_weight_power=2.0))
