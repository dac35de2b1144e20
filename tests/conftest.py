from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
PROFILES = ROOT / "config" / "profiles"  # the four real profiles ship in the repository (MIT)
VECTORS = Path(__file__).resolve().parent / "vectors"

# (file, loader options) for the four real instrument files; units per their README.
REAL = {
    "dektak-1.csv": {"x_unit": "um", "y_unit": "um"},
    "xy-4.txt": {"x_unit": "mm", "y_unit": "um"},
    "xy-1.txt": {"x_unit": "um", "y_unit": "um"},
    "opdx-3.txt": {"x_unit": "m", "y_unit": "m"},
}


def real_profile_path(name: str) -> Path:
    p = PROFILES / name
    if not p.exists():
        pytest.skip(f"real profile {name} not present in {PROFILES}")
    return p


@pytest.fixture
def rng():
    return np.random.default_rng(12345)

# Reference speed per file (mm/s) so that the patch holds at least a few components below
# 400 Hz: opdx-3 is only 50 µm long, so at 50 mm/s its first component would be 500 Hz.
REAL_SPEED = {"dektak-1.csv": 50.0, "xy-4.txt": 50.0, "xy-1.txt": 5.0, "opdx-3.txt": 0.5}
