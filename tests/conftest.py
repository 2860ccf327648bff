"""Shared test set-up.

Every test runs with its own empty user data directory (`NOISESTOP_DATA_DIR`), so a
calibration or pre-training in the developer's real one (`noisefeat.userdata`) never changes
what the tests measure, and no test writes there.

With NOISESTOP_TEST_LLVM_TARGET set ("haswell,8"), Dr.Jit's LLVM backend compiles every
kernel of this process for that CPU (`make test-portability`): the suite must
pass on code another CPU would generate.
"""
from __future__ import annotations

import os
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True, scope="session")
def _isolated_user_data(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    from noisefeat.userdata import ENV

    old = os.environ.get(ENV)
    os.environ[ENV] = str(tmp_path_factory.mktemp("user-data"))
    yield
    if old is None:
        os.environ.pop(ENV, None)
    else:
        os.environ[ENV] = old


@pytest.fixture(autouse=True, scope="session")
def _llvm_target() -> None:
    if not os.environ.get("NOISESTOP_TEST_LLVM_TARGET"):
        return
    from tests.support.passloop_golden import apply_target_from_env

    target = apply_target_from_env()
    if target:
        print(f"\nDr.Jit's LLVM backend compiles for {target} (NOISESTOP_TEST_LLVM_TARGET)")
