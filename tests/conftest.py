import pytest

from companion.cli import single_thread_blas


@pytest.fixture(autouse=True, scope="session")
def _single_thread_blas():
    # Same setting as the CLIs: small matrices are much slower with threaded BLAS.
    with single_thread_blas():
        yield
