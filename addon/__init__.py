"""skinsafe Blender extension: design tactile skins on robots (placement, per-taxel frames,
Jacobian heat maps, boards, coverage, export). Logic lives in skinsafe.core; this package
adapts Blender data and draws.

Registers properties, then operators, then panels, drawing, handlers and the toolbar's tool; unregisters in
reverse.
"""
from skinsafe.addon import (
    cover,
    deploy,
    drawing,
    findings,
    handlers,
    live,
    operators,
    panels,
    pfl,
    place_tool,
    props,
    toolbar,
)

_MODULES = (props, operators, cover, place_tool, findings, deploy, panels, pfl, drawing, handlers, live, toolbar)


def register():
    for m in _MODULES:
        m.register()


def unregister():
    for m in reversed(_MODULES):
        m.unregister()
    from skinsafe.addon import blender_to_core
    blender_to_core.clear_caches()
