from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def shared(*parts) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"third-party test data not available: {p} (../shared/data is absent)")
    return p


@pytest.fixture(scope="session")
def hand():
    from handmodel import HandModel

    return HandModel.load()


@pytest.fixture(scope="session")
def fingerfist():
    """The 6000×26 fingerfist postures (global translation in mm as in the file)."""
    return np.loadtxt(shared("htrack_schroeder", "fingerfist.txt"))
