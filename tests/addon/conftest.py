"""The add-on registered once per test module, and unregistered without leaving a handler behind."""
import bpy
import pytest

import skinsafe.addon as addon
from skinsafe.addon import edits


@pytest.fixture(scope="module", autouse=True)
def registered():
    addon.register()
    yield
    addon.unregister()
    assert not any(getattr(f, "__module__", "").startswith("skinsafe") for f in bpy.app.handlers.depsgraph_update_post)
    assert not bpy.app.timers.is_registered(edits._after_transform)  # a timer left would hang the process at exit
