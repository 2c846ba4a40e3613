"""ISO/TS 15066:2016 Annex A body regions: force and pressure limits, effective masses, spring
constants.

The person in a scene (`human.py`) and the PFL speed limits (`skinsafe.core.safety.pfl`) read the
same table. Sources:

- ISO/TS 15066:2016, Annex A: Table A.2 (maximum permissible quasi-static force per body region
  and maximum permissible quasi-static pressure per specific body area; transient contact up to
  twice both, none for the skull/forehead and the face) and Table A.3 (effective masses and
  spring constants of the body regions). Head 4.4 kg is the ISO/TS 15066 value (8.8 kg circulates
  in secondary tables; a heavier head would allow a lower robot speed only through mu, and no
  transient head contact is allowed anyway).
- The pressure of a region is the lowest of its specific body areas (the robot cannot tell which
  part of the region it meets): skull 110 (temple; forehead 130), face 110 (masticatory muscle),
  neck 140 (neck muscle; seventh neck muscle 210), back/shoulders 160 (shoulder joint; fifth lumbar
  vertebra 210), chest 120 (sternum; pectoral muscle 170), abdomen 140, pelvis 210, upper arm 190
  (deltoid; humerus 220), lower arm 180 (forearm muscle and arm nerve; radial bone 190), hand 190
  (back of the non-dominant hand; palm 260, forefinger pad 270-300, thenar eminence 200), thigh 220
  (kneecap; thigh muscle 250), lower leg 210 (calf muscle; middle of the shin 220), N/cm^2.
- Second sources, checked by `tests/safety/test_pfl_math.py`: the transient forces of
  ISO 10218-2:2025 Annex A in the PFL calculator at https://safety.stimba.sk/en/pfl (back 420,
  chest 280, abdomen 220, pelvis 360, upper arm 300, forearm 320, hand 280 N: twice the
  quasi-static values below; m_H of the back 40 kg) and the spring constants listed at
  https://inmotion-v2-preview.pages.dev/resources/cobot-safety/iso-ts-15066-body-region-force-limits/
  (skull 150, face 75, neck 50, back 35, chest 25, belly 10 N/mm). Tables with about half these
  forces (the older BG/BGIA pain-onset values) also circulate; they are not ISO/TS 15066.

Contact kinds (`KINDS`): `transient` (the body part can recoil: twice the quasi-static force and
pressure), `quasi_static` (it cannot, e.g. pinched between two links) and `clamp` (trapped
against a fixed surface): the quasi-static force and pressure, from the first instant.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("transient", "quasi_static", "clamp")


@dataclass(frozen=True)
class Region:
    """One body region of ISO/TS 15066 Annex A (SI units; pressure in N/cm^2 as the table gives it)."""

    name: str
    label: str
    quasi_static_N: float  # Table A.2, maximum permissible quasi-static force
    transient_N: float | None  # 2x quasi-static; None: no transient contact allowed
    mass_kg: float  # Table A.3, effective mass of the body region
    k_N_per_m: float  # Table A.3, effective spring constant
    pressure_N_cm2: float  # Table A.2, maximum permissible quasi-static pressure (lowest specific area)

    def transient_limit(self) -> float:
        """The transient force limit (N); 0 where no transient contact is allowed."""
        return 0.0 if self.transient_N is None else self.transient_N

    def force_limit(self, kind: str) -> float:
        """The force limit (N) of a contact of `kind` (`KINDS`)."""
        return self.transient_limit() if _kind(kind) == "transient" else self.quasi_static_N

    def pressure_limit(self, kind: str) -> float:
        """The pressure limit (N/cm^2) of a contact of `kind`; 0 for a transient one where none is allowed."""
        if _kind(kind) != "transient":
            return self.pressure_N_cm2
        return 0.0 if self.transient_N is None else 2.0 * self.pressure_N_cm2


def _kind(kind: str) -> str:
    if kind not in KINDS:
        raise ValueError(f"contact kind '{kind}' is unknown; use one of {', '.join(KINDS)}")
    return kind


def _region(name, label, fqs, transient, mass, k_n_per_mm, pressure) -> Region:
    return Region(name, label, float(fqs), 2.0 * fqs if transient else None, float(mass), 1e3 * k_n_per_mm,
                  float(pressure))


REGIONS: dict[str, Region] = {r.name: r for r in (
    _region("skull", "skull/forehead", 130, False, 4.4, 150, 110),
    _region("face", "face", 65, False, 4.4, 75, 110),
    _region("neck", "neck", 150, True, 1.2, 50, 140),
    _region("back", "back/shoulders", 210, True, 40, 35, 160),
    _region("chest", "chest", 140, True, 40, 25, 120),
    _region("abdomen", "abdomen", 110, True, 40, 10, 140),
    _region("pelvis", "pelvis", 180, True, 40, 25, 210),
    _region("upper_arm", "upper arm/elbow", 150, True, 3, 30, 190),
    _region("lower_arm", "lower arm/wrist", 160, True, 2, 40, 180),
    _region("hand", "hand/finger", 140, True, 0.6, 75, 190),
    _region("thigh", "thigh/knee", 220, True, 75, 50, 220),
    _region("lower_leg", "lower leg", 130, True, 75, 60, 210),
)}


def region(name: str) -> Region:
    """The region called `name`; an unknown name is a ValueError listing the known ones."""
    try:
        return REGIONS[name]
    except KeyError:
        raise ValueError(f"body region '{name}' is unknown; use one of {', '.join(REGIONS)}") from None


def contact_areas(design) -> np.ndarray:
    """(N,) m^2: the skin area each taxel stands for, its module's cell (pitch^2). The readout gives
    every taxel the force through its cell (a contact's force is shared among the taxels around it,
    summing to the contact force), so a taxel's pressure is its force over its cell; the taxel's own
    sensing area (`Taxels.area`, the FSR disc, 28% of a sample cell) would overstate it."""
    pitch = {m.id: m.pitch for m in design.modules}
    t = design.taxels
    return np.array([pitch.get(int(m), np.sqrt(a / np.pi) * 2) ** 2 for m, a in zip(t.module, t.area)], float)
