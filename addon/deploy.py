"""Boards and Deploy (View3D > N > Skin > Boards): the design's interface boards with their channel use,
and Deploy: the boards found on the given ports (or every serial port) by unique id, each sent its config
and read back as `skinsafe deploy` does (hardware/deploy.py); from the panel a dry run comes first and a
confirmation names what would change. Each board's named outcome is listed. Works the same against
emulated boards (`skinsafe emulate`'s ports). pyserial is imported on Deploy only."""
import bpy
from bpy.props import BoolProperty, StringProperty

from skinsafe.addon import background
from skinsafe.addon import blender_to_core as b2c


class SkinsafeDeploy(bpy.types.PropertyGroup):
    ports: StringProperty(name="Ports", default="",
                          description="serial ports or globs (e.g. /tmp/boards/board-*), ';'-separated; empty: every "
                                      "serial port of this computer")
    outcome: StringProperty(default="")  # one line per board of the last run


def _design(context):
    design = b2c.design_of(context.scene)
    return design if design is not None and design.boards else None


def run(design, entries: list[str], dry_run: bool, cancel=None):
    """The boards' reports (each board of the design: found and deployed, or missing with why), by board id.
    `cancel` (`background.Cancel`): once requested, boards not yet reached are not sent anything."""
    from skinsafe.hardware.deploy import candidate_ports, deploy, discover, missing_reports, plan

    globs = [e for e in entries if any(c in e for c in "*?[")]
    ports = [e for e in entries if e not in globs] + candidate_ports(globs, system=not entries)
    p = plan(design, discover(ports, cancel=cancel))
    reports = deploy(design, p.ports, dry_run, configs=p.configs, cancel=cancel) if p.ports else []
    return sorted(reports + missing_reports(design, p), key=lambda r: r.board.id)


class SKINSAFE_OT_deploy(background.Modal, bpy.types.Operator):
    """Send the skin's board configs to the interface boards (found by unique id) and read them back;
    Dry Run only says what would change"""

    bl_idname = "skinsafe.deploy"
    bl_label = "Deploy"

    dry_run: BoolProperty(name="Dry run", default=True, description="change nothing: say what a deploy would change")

    poll = classmethod(lambda cls, context: _design(context) is not None)
    reports = ()  # the last run's BoardReports

    def invoke(self, context, event):
        """Deploy from the panel: a dry run first (seconds: identify and compare), then a confirmation naming
        what would change, then the deploy."""
        if self.dry_run:
            return self.execute(context)
        self.dry_run = True
        job = self._job(context)
        job.wait()
        checked = self.finish(context, job)
        self.dry_run = False
        if checked != {"FINISHED"}:
            return checked
        what = ", ".join(f"{r.board.name} {r.status}" + (f" (channels +{c['added']} -{c['removed']} ~{c['changed']})"
                                                         if (c := r.changes) else "") for r in self.reports)
        return context.window_manager.invoke_confirm(self, event, title="Deploy to the boards?", message=what,
                                                     confirm_text="Deploy", icon="WARNING")

    def execute(self, context):
        """The boards are handled off Blender's thread where there is an event loop; Esc stops: boards not yet
        reached are sent nothing, and a board's commit is atomic, so each runs its old or its new config."""
        job = self._job(context)
        if not bpy.app.background:
            return self.start(context, job, self.finish, "checking the boards" if self.dry_run else "deploying")
        job.wait()
        return self.finish(context, job)

    def _job(self, context):
        dep, cancel = context.window_manager.skinsafe_deploy, background.Cancel()
        return background.Job(run, _design(context), [e.strip() for e in dep.ports.split(";") if e.strip()],
                              self.dry_run, cancel, cancel=cancel)

    def finish(self, context, job):
        dep = context.window_manager.skinsafe_deploy
        if job.error is not None:  # pyserial missing, or a design the boards cannot take (DesignError)
            dep.outcome = (f"Deploy needs pyserial ({job.error}); install the add-on's zip with its wheels, or use "
                           "skinsafe deploy") if isinstance(job.error, ImportError) else str(job.error)
            self.report({"ERROR"}, dep.outcome)
            return {"CANCELLED"}
        self.reports = reports = job.result
        dep.outcome = "\n".join(r.line() for r in reports)
        bad = [r for r in reports if not r.ok]
        what = "checked" if self.dry_run else "deployed"
        if bad:
            self.report({"ERROR"}, f"{len(bad)} of {len(reports)} boards not {what}; the first: {bad[0].line()}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"{len(reports)} boards {what}: " + ", ".join(sorted({r.status for r in reports})))
        return {"FINISHED"}


class SKINSAFE_PT_boards(bpy.types.Panel):
    bl_space_type, bl_region_type, bl_category = "VIEW_3D", "UI", "Skin"
    bl_idname = "SKINSAFE_PT_boards"
    bl_label = "Boards"

    def draw(self, context):
        col, design = self.layout.column(), _design(context)
        if design is None:
            col.label(text="no boards (place modules, then Assign Boards)")
            return
        for b in design.boards:
            used = int((design.taxels.board == b.id).sum())
            col.label(text=f"{b.name} uid {b.uid:#x}: {used}/{b.capacity} channels")
        dep = context.window_manager.skinsafe_deploy
        col.prop(dep, "ports")
        row = col.row(align=True)
        row.operator("skinsafe.deploy", text="Dry Run").dry_run = True
        row.operator("skinsafe.deploy", text="Deploy").dry_run = False
        for line in dep.outcome.splitlines():
            col.label(text=line)


CLASSES = (SkinsafeDeploy, SKINSAFE_OT_deploy, SKINSAFE_PT_boards)
_register, _unregister = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register()
    bpy.types.WindowManager.skinsafe_deploy = bpy.props.PointerProperty(type=SkinsafeDeploy)


def unregister():
    del bpy.types.WindowManager.skinsafe_deploy
    _unregister()
