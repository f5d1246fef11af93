"""Replica (NICE-SLAM renders, 1200x680, exact depth): paper settings R = 10, K_c = 10.

T's voxels and correspondence limit scale with the points' spacing: 6 cm at R = 10 as 3 cm at
R = 5 (on Replica with a simulated structured-light sensor, 3 cm lost to small_gicp, 6 cm beat it;
docs/method.md, "Depth outliers").
"""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="replica", data=DataConfig(layout="auto"), track=TrackConfig(stride=10, k=10, voxel_size=0.06, max_correspondence=0.06))
