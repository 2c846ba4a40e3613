"""skinsafe Blender extension: design tactile skins on robots (placement, per-taxel frames,
Jacobian heat maps, boards, coverage, export). Logic lives in skinsafe.core; this package
adapts Blender data and draws.

One module per feature (docs/design/addon.md lists them). Registers properties, then operators, then panels,
the frames' overlay, the edits' app handlers, Live and the toolbar's tool; unregisters in reverse. The
operators and panels of robot, fpc_modules, analysis, check, export and frames register here as two steps
(`OPERATORS`, `PANELS`): the sidebar lists panels in the order they register (Check, Boards, Robot, FPC Modules,
Frames/Jacobians/Boards, PFL, Live).
"""
from types import SimpleNamespace

import bpy

from skinsafe.addon import (
    analysis,
    check,
    cover,
    deploy,
    edits,
    export,
    findings,
    fpc_modules,
    frames,
    live,
    pfl,
    place_tool,
    props,
    robot,
    toolbar,
)


def _classes(*features):
    """One registration step: the classes of these feature modules, in this order."""
    register, unregister = bpy.utils.register_classes_factory(tuple(c for f in features for c in f))
    return SimpleNamespace(register=register, unregister=unregister)


_OPERATORS = _classes(robot.OPERATORS, fpc_modules.OPERATORS, analysis.OPERATORS, check.OPERATORS, export.OPERATORS,
                      frames.OPERATORS)
_PANELS = _classes(robot.PANELS, fpc_modules.PANELS, analysis.PANELS)
_MODULES = (props, _OPERATORS, export, cover, place_tool, findings, deploy, _PANELS, pfl, frames, edits, live, toolbar)


def register():
    for m in _MODULES:
        m.register()


def unregister():
    for m in reversed(_MODULES):
        m.unregister()
    from skinsafe.addon import blender_to_core
    blender_to_core.clear_caches()
