"""Designing a skin without Blender: link surfaces, conformal FPC module placement, coverage and
the sample skins. May import `skin` and `robot`."""
