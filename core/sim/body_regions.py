"""ISO/TS 15066:2016 Annex A body regions: force limits, effective masses, spring constants.

The person in a scene (`human.py`) and the PFL speed limits (`skinsafe.core.safety.pfl`) read the
same table. Sources:

- ISO/TS 15066:2016, Annex A: Table A.2 (maximum permissible quasi-static force per body region;
  transient contact up to twice that, none for the skull/forehead and the face; effective spring
  constants) and Table A.3 (effective masses of the body regions). Head 4.4 kg is the ISO/TS 15066
  value (8.8 kg circulates in secondary tables; a heavier head would allow a lower robot speed
  only through mu, and no transient head contact is allowed anyway).
- Second sources, checked by `tests/safety/test_pfl_math.py`: the transient forces of
  ISO 10218-2:2025 Annex A in the PFL calculator at https://safety.stimba.sk/en/pfl (back 420,
  chest 280, abdomen 220, pelvis 360, upper arm 300, forearm 320, hand 280 N: twice the
  quasi-static values below; m_H of the back 40 kg) and the spring constants listed at
  https://inmotion-v2-preview.pages.dev/resources/cobot-safety/iso-ts-15066-body-region-force-limits/
  (skull 150, face 75, neck 50, back 35, chest 25, belly 10 N/mm). Tables with about half these
  forces (the older BG/BGIA pain-onset values) also circulate; they are not ISO/TS 15066.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Region:
    """One body region of ISO/TS 15066 Annex A (SI units)."""

    name: str
    label: str
    quasi_static_N: float  # Table A.2, maximum permissible quasi-static force
    transient_N: float | None  # 2x quasi-static; None: no transient contact allowed
    mass_kg: float  # Table A.3, effective mass of the body region
    k_N_per_m: float  # Table A.2, effective spring constant

    def transient_limit(self) -> float:
        """The transient force limit (N); 0 where no transient contact is allowed."""
        return 0.0 if self.transient_N is None else self.transient_N


def _region(name, label, fqs, transient, mass, k_n_per_mm) -> Region:
    return Region(name, label, float(fqs), 2.0 * fqs if transient else None, float(mass), 1e3 * k_n_per_mm)


REGIONS: dict[str, Region] = {r.name: r for r in (
    _region("skull", "skull/forehead", 130, False, 4.4, 150),
    _region("face", "face", 65, False, 4.4, 75),
    _region("neck", "neck", 150, True, 1.2, 50),
    _region("back", "back/shoulders", 210, True, 40, 35),
    _region("chest", "chest", 140, True, 40, 25),
    _region("abdomen", "abdomen", 110, True, 40, 10),
    _region("pelvis", "pelvis", 180, True, 40, 25),
    _region("upper_arm", "upper arm/elbow", 150, True, 3, 30),
    _region("lower_arm", "lower arm/wrist", 160, True, 2, 40),
    _region("hand", "hand/finger", 140, True, 0.6, 75),
    _region("thigh", "thigh/knee", 220, True, 75, 50),
    _region("lower_leg", "lower leg", 130, True, 75, 60),
)}


def region(name: str) -> Region:
    """The region called `name`; an unknown name is a ValueError listing the known ones."""
    try:
        return REGIONS[name]
    except KeyError:
        raise ValueError(f"body region '{name}' is unknown; use one of {', '.join(REGIONS)}") from None
