"""The collaboration experiment's results: contact events from a run's person trace (`contact_events`, judged
against ISO/TS 15066's limits per body region), the result file (`summarise`), its Markdown tables and its figure."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from skinsafe.core.experiments.collaboration_scenario import NOMINAL, ROBOT_DRIVEN, SCENARIOS, STACKS, CollabConfig

TRANSIENT_S = 0.5  # ISO/TS 15066: transient contact lasts up to 0.5 s; a longer push is quasi-static
GAP_S = 0.1  # force-free gaps shorter than this do not end a contact event



def contact_events(trace: dict, regions: list[str], control_dt: float, acted=None, body_names=None) -> list[dict]:
    """Contact events per body part from a person trace (`arm_scene.PersonTrace.arrays`): module
    docstring. `acted` (ticks, 3) bool: defensiveness, pfl, modulation acting per control tick."""
    from skinsafe.core.sim.body_regions import region

    t = trace["time_s"]
    if not len(t):
        return []
    dt = float(np.median(np.diff(t))) if len(t) > 1 else control_dt
    gap = max(1, int(round(GAP_S / dt)))
    n_tr = int(round(TRANSIENT_S / dt))
    out = []
    for j, name in enumerate(regions):
        reg = region(name)
        f = trace["force_N"][:, j]
        on = np.flatnonzero(f > 0)
        if not len(on):
            continue
        breaks = np.flatnonzero(np.diff(on) > gap)
        for a, b in zip(np.r_[on[0], on[breaks + 1]], np.r_[on[breaks], on[-1]]):
            sl = slice(a, b + 1)
            fe, pe = f[sl], trace["pressure_N_cm2"][sl, j]
            kind = ("clamp" if trace["trapped"][sl, j].any() else
                    "quasi_static" if trace["pinched"][sl, j].any() else "transient")
            first = slice(0, n_tr) if kind == "transient" else slice(None)
            rest = slice(n_tr, None) if kind == "transient" else slice(0, 0)
            peak, peak_p = float(fe[first].max()), float(pe[first].max())
            qs = float(fe[rest].max()) if len(fe[rest]) else 0.0
            qs_p = float(pe[rest].max()) if len(pe[rest]) else 0.0
            lim, lim_p = reg.force_limit(kind), reg.pressure_limit(kind)
            ratios = [_ratio(peak, lim), _ratio(qs, reg.quasi_static_N), _ratio(peak_p, lim_p),
                      _ratio(qs_p, reg.pressure_N_cm2)]
            sensed = np.flatnonzero(trace["sensed"][sl, j])
            bare = (fe > 0) & ~trace["touched"][sl, j]
            bodies = trace["body"][sl, j]
            link = int(bodies[np.argmax(fe)])
            ticks = slice(int(t[a] // control_dt), int(t[b] // control_dt) + 2)
            layers = [n for n, on_ in zip(("defensiveness", "pfl", "modulation"),
                                          acted[ticks].any(axis=0) if acted is not None and len(acted[ticks]) else ())
                      if on_]
            out.append({"region": name, "kind": kind, "start_s": round(float(t[a]), 4),
                        "duration_s": round(float(t[b] - t[a] + dt), 4),
                        "peak_N": peak, "limit_N": lim, "quasi_static_N": qs, "quasi_static_limit_N": reg.quasi_static_N,
                        "peak_pressure_N_cm2": peak_p, "pressure_limit_N_cm2": lim_p,
                        "quasi_static_pressure_N_cm2": qs_p, "quasi_static_pressure_limit_N_cm2": reg.pressure_N_cm2,
                        "ratio": max(ratios), "within": bool(max(ratios) <= 1.0),
                        "sensed": bool(len(sensed)), "sensed_ms": round(1e3 * float(t[a + sensed[0]] - t[a]), 2)
                        if len(sensed) else None,
                        "bare_ms": round(1e3 * float(bare.sum()) * dt, 2),
                        "robot_link": body_names[link] if body_names is not None and link >= 0 else str(link),
                        "acted": "+".join(layers) or "none"})
    return sorted(out, key=lambda e: e["start_s"])


def _ratio(value: float, limit: float) -> float:
    if value <= 0:
        return 0.0
    return value / limit if limit > 0 else float("inf")


def summarise(nominal: list, sweep: list, design, cfg: CollabConfig) -> dict:
    """The result file: contact rows and run summaries of the nominal cells, the sweep table, the
    findings (contacts the skin did not sense; limits exceeded by full+pfl)."""
    out = {"config": cfg.to_json(), "nominal": NOMINAL, "skin_taxels": design.n_taxels, "skin_modules": len(design.modules),
           "contacts": [], "runs": {}, "sweep": [], "findings": []}
    for r in nominal:
        for stack, res in r["stacks"].items():
            for e in res["events"]:
                out["contacts"].append({"scenario": r["scenario"], "stack": stack, **e})
            ev = res["events"]
            out["runs"][f"{r['scenario']}/{stack}"] = {
                "events": len(ev), "within": all(e["within"] for e in ev), "sensed": all(e["sensed"] for e in ev),
                "peak_N": max((max(e["peak_N"], e["quasi_static_N"]) for e in ev), default=0.0),
                "worst_ratio": max((e["ratio"] for e in ev), default=0.0),
                "task_time_s": res["task_time_s"], "no_person_task_time_s": res.get("no_person_task_time_s"),
                "force_N": res["force_N"], "pan_rad": res["pan_rad"]}
    none_peak = {}
    for r in sweep:
        for stack, res in r["stacks"].items():
            ev = res["events"]
            worst = max(ev, key=lambda e: e["ratio"], default=None)
            row = {"scenario": r["scenario"], "stack": stack, "damping_ratio": r["damping_ratio"],
                   "attachment_N_m": r["attachment_N_m"], "dt_ms": r["dt_ms"],
                   "worst_ratio": worst["ratio"] if worst else 0.0,
                   "peak_N": max((max(e["peak_N"], e["quasi_static_N"]) for e in ev), default=0.0),
                   "peak_pressure_N_cm2": max((e["peak_pressure_N_cm2"] for e in ev), default=0.0),
                   "kind": worst["kind"] if worst else None, "events": len(ev),
                   "sensed": all(e["sensed"] for e in ev), "unstable": res.get("unstable", 0)}
            key = (r["scenario"], r["damping_ratio"], r["attachment_N_m"], r["dt_ms"])
            if stack == "none":
                none_peak[key] = row["peak_N"]
            out["sweep"].append(row)
    for row in out["sweep"]:
        base = none_peak.get((row["scenario"], row["damping_ratio"], row["attachment_N_m"], row["dt_ms"]))
        row["peak_vs_none"] = row["peak_N"] / base if base else None
    for e in out["contacts"]:
        if not e["sensed"]:
            out["findings"].append(f"{e['scenario']}/{e['stack']}: {e['region']} contact at {e['start_s']} s on "
                                   f"{e['robot_link']} was not sensed (bare surface {e['bare_ms']} ms)")
    for r in nominal + sweep:
        for stack, res in r["stacks"].items():
            if res.get("unstable"):
                out["findings"].append(f"{r['scenario']}/{stack} zeta {r['damping_ratio']} attach {r['attachment_N_m']} "
                                       f"dt {r['dt_ms']} ms: the simulation blew up and MuJoCo reset it")
    for row in out["sweep"]:
        if row["stack"] == "full+pfl" and row["scenario"] in ROBOT_DRIVEN and row["worst_ratio"] > 1:
            out["findings"].append(f"sweep {row['scenario']} zeta {row['damping_ratio']} attach {row['attachment_N_m']} "
                                   f"dt {row['dt_ms']} ms: full+pfl at {row['worst_ratio']:.2f} of its limit")
    return out



def trace_every(dt_ms: float) -> int:
    """Physics steps per sample of the detail cells' force trace (about 1 ms)."""
    return max(1, int(round(1.0 / dt_ms)))


def tables(res: dict) -> str:
    """The result as Markdown (collaboration.md): `nominal_table` and `sweep_table`."""
    sweep = sweep_table(res)
    return nominal_table(res) + ("\n\n" + sweep if sweep else "") + "\n"


def nominal_table(res: dict) -> str:
    """The nominal runs per scenario and stack: contacts, the worst ratio and its contact, peaks,
    sensing, the layers that acted, task times."""
    lines = ["| scenario | stack | contacts | worst ratio (kind, region) | peak N (N/cm^2) | sensed (latest, ms) "
             "| layers that acted | task s (no person) |", "| --- | --- | ---: | --- | ---: | --- | --- | ---: |"]
    for key, r in res["runs"].items():
        scenario, stack = key.split("/")
        ev = [e for e in res["contacts"] if e["scenario"] == scenario and e["stack"] == stack]
        worst = max(ev, key=lambda e: e["ratio"], default=None)
        late = max((e["sensed_ms"] or 0 for e in ev), default=0)
        acted = sorted({a for e in ev for a in e["acted"].split("+")} - {"none"}) or ["none"]
        task = "-" if r["task_time_s"] is None else f"{r['task_time_s']:.2f}"
        if r["no_person_task_time_s"] is not None:
            task += f" ({r['no_person_task_time_s']:.2f})"
        lines.append(f"| {scenario} | {stack} | {len(ev)} | "
                     + (f"{worst['ratio']:.2f} ({worst['kind']}, {worst['region']})" if worst else "-")
                     + f" | {r['peak_N']:.0f} ({max((e['peak_pressure_N_cm2'] for e in ev), default=0):.0f}) | "
                     + ("all" if r["sensed"] else "**not all**") + f" ({late:.1f}) | {'+'.join(acted)} | {task} |")
    return "\n".join(lines)


def sweep_table(res: dict) -> str:
    """The sweep's worst ratio per cell (`none` / `full+pfl`), with the person-driven cells'
    full+pfl peak over the `none` run's; empty without a sweep."""
    rows, lines = res["sweep"], []
    cells = sorted({(r["damping_ratio"], r["attachment_N_m"]) for r in rows})
    if cells:
        lines = ["| scenario | dt ms | " + " | ".join(f"zeta {z:g}, {k:g} N/m" for z, k in cells) + " |",
                 "| --- | ---: | " + " | ".join("---:" for _ in cells) + " |"]
        for scenario in SCENARIOS:
            for dt in sorted({r["dt_ms"] for r in rows}, reverse=True):
                out = []
                for z, k in cells:
                    by = {r["stack"]: r for r in rows if (r["scenario"], r["dt_ms"], r["damping_ratio"],
                                                          r["attachment_N_m"]) == (scenario, dt, z, k)}
                    txt = " / ".join(f"{by[s]['worst_ratio']:.2f}" for s in ("none", "full+pfl") if s in by)
                    if scenario not in ROBOT_DRIVEN and by.get("full+pfl", {}).get("peak_vs_none") is not None:
                        txt += f" (x{by['full+pfl']['peak_vs_none']:.2f})"
                    out.append(txt or "-")
                lines.append(f"| {scenario} | {dt:g} | " + " | ".join(out) + " |")
    return "\n".join(lines)


def save_plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")

    from skinsafe.core.skin.files import write_png

    fig = plot(res)
    write_png(fig, path)


def plot(res: dict):
    """Force on the person per scenario and stack (nominal cell), and every contact's and sweep
    cell's worst ratio to its ISO/TS 15066 limit."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
    dt_ms = res["nominal"]["dt_ms"]
    period = trace_every(dt_ms) * dt_ms / 1e3  # s per sample of the force traces
    for ax, scenario in zip(axes[0], SCENARIOS):
        hit = [e["start_s"] for e in res["contacts"] if e["scenario"] == scenario]
        for stack in STACKS:
            f = res["runs"].get(f"{scenario}/{stack}", {}).get("force_N", [])
            ax.plot(np.arange(len(f)) * period, f, label=stack, lw=1)
        if hit:
            ax.set_xlim(min(hit) - 0.1, max(hit) + 0.6)
        ax.set_title(f"{scenario}: force on the person")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("normal force on the person (N)")
        ax.legend(fontsize=7)
    ax = axes[1, 0]
    rows = res["contacts"]
    ax.bar(range(len(rows)), [min(e["ratio"], 3) for e in rows],
           color=["tab:red" if not e["within"] else "tab:green" for e in rows])
    ax.set_xticks(range(len(rows)), [f"{e['scenario'][:5]}/{e['stack']}\n{e['region']}" for e in rows], fontsize=5,
                  rotation=90)
    ax.axhline(1, color="k", lw=0.8)
    ax.set_ylabel("peak / ISO/TS 15066 limit (ratio, force or pressure)")
    ax.set_xlabel("contact (scenario/stack, region)")
    ax.set_title("nominal contacts")
    ax = axes[1, 1]
    for k, scenario in enumerate(SCENARIOS):
        for stack, marker in (("none", "x"), ("full+pfl", "o")):
            rows = [r for r in res["sweep"] if r["scenario"] == scenario and r["stack"] == stack]
            ax.scatter(np.arange(len(rows)) + 0.25 * k, [r["worst_ratio"] for r in rows], marker=marker, s=14,
                       label=f"{scenario} {stack}")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xlabel("sweep cell (number: damping x attachment x timestep)")
    ax.set_ylabel("worst peak / limit (ratio)")
    ax.set_title("robustness sweep")
    ax.legend(fontsize=6)
    ax = axes[1, 2]
    rows = [r for r in res["sweep"] if r["scenario"] == "person" and r["stack"] != "none"]
    ax.bar(range(len(rows)), [r["peak_vs_none"] or 0 for r in rows], color="tab:blue")
    ax.axhline(1, color="k", lw=0.8)
    ax.set_xlabel("sweep cell (number: damping x attachment x timestep)")
    ax.set_ylabel("peak with full+pfl / without safety (ratio)")
    ax.set_title("person moving into the still robot")
    if not res["sweep"]:  # a nominal-only run (--no-sweep): say so instead of drawing empty axes
        for ax in axes[1, 1:]:
            ax.cla()
            ax.set_axis_off()
            ax.text(0.5, 0.5, "sweep not run here (--no-sweep);\nthe full run: skinsafe experiment collaboration",
                    ha="center", va="center", fontsize=9, transform=ax.transAxes)
    fig.tight_layout()
    return fig
