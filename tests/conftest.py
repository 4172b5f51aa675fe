import os

# small matrices: BLAS threads only contend (must be set before numpy loads)
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

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
