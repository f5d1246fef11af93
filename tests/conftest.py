import os
import pathlib

import pytest

SHARED_DATA = pathlib.Path(os.environ.get("SGAD_SHARED_DATA", pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"))


def shared(name: str) -> pathlib.Path:
    """A folder of ../shared/data, or skip the test when it is absent."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data {path} not available (set SGAD_SHARED_DATA to the shared/data folder)")
    return path
