"""ScanNet++ DSLR (876x584 after the usual half-size resize): paper settings R = 10, K_c = 10.

T's voxels and correspondence limit 6 cm, as Replica's at the same stride (configs/replica.py).
"""

from sgad_jax.config import DataConfig, SLAMConfig, TrackConfig


def get_config() -> SLAMConfig:
    return SLAMConfig(name="scannetpp", data=DataConfig(layout="auto"), track=TrackConfig(stride=10, k=10, voxel_size=0.06, max_correspondence=0.06))
