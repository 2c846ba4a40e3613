"""What the operators of several features share (robot, fpc_modules, analysis, check, export, frames): their
polls (a robot imported, a skin placed) and how they end (the panel's message or error, and a report). Not a
feature of its own: each of those modules would otherwise repeat it."""


def fail(op, scene, e: Exception):
    scene.skinsafe.error = str(e)
    op.report({"ERROR"}, str(e))
    return {"CANCELLED"}


def ok(op, scene, msg: str):
    scene.skinsafe.error = ""
    scene.skinsafe.message = msg
    op.report({"INFO"}, msg)
    return {"FINISHED"}


def has_robot(context):
    return bool(context.scene.skinsafe.robot_kind)


def has_skin(context):
    return has_robot(context) and any(o.skinsafe_module.is_module for o in context.scene.objects)
