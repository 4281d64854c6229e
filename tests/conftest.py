"""Every test draws helpers.weights() from a generator reseeded from its own id, so its values do not
depend on which tests ran before it in the same worker (pytest-xdist distributes tests differently
from run to run)."""

import zlib

import numpy as np
import pytest
from helpers import RNG


@pytest.fixture(autouse=True)
def _weights_seeded_per_test(request):
    RNG.bit_generator.state = np.random.PCG64(zlib.crc32(request.node.nodeid.encode())).state
