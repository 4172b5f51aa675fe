import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def profile():
    from ffcomp.profile import default_profile

    return default_profile()


@pytest.fixture(scope="session")
def model(profile):
    from ffcomp.model import LpvModel

    return LpvModel.from_profile(profile)


@pytest.fixture(scope="session")
def geom(profile):
    return profile.geometry_si()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
