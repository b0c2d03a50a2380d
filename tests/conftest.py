"""Shared set-up of the test suite, which mirrors ``src/tissuecast`` (``tests/fem/`` tests
``tissuecast.fem`` and so on; the top-level modules and the package-wide checks are here).

The helper modules in this folder (``mesh_factories``, ``labelmap_factories``,
``dataset_helpers``, ``serve_support``, ``_surrogate_synthetic``, ``_trust_synthetic``,
``_instrument_synthetic``, ``_browser``) are imported by tests in every subfolder: this folder
goes first on ``sys.path`` (worker processes spawned by a test inherit it, so a fake solver
factory named ``"dataset_helpers:fake_solver_factory"`` imports there too). Shared data lives in
``tests/data``, the OpenIGTLink C++ client in ``tests/igtl_client``.
"""

import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))
