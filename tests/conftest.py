"""Test set-up shared by all suites.

bpy is imported first: pymeshlab and bpy both bundle Embree, and bpy fails to import after pymeshlab.
"""
import bpy  # noqa: F401  (must precede any pymeshlab import)
import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny networks: one torch thread avoids oversubscribing the shared 2-core machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
