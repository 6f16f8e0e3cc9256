from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BUNDLED_SCAN = REPO / "data" / "raw" / "dtu" / "scan24"


@pytest.fixture(scope="session")
def bundled_scan() -> Path:
    assert (BUNDLED_SCAN / "cameras_sphere.npz").is_file(), "bundled scan24 subset missing from the repository"
    return BUNDLED_SCAN
