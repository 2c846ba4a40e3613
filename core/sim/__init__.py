"""Simulating what a skin feels: MuJoCo scenes built from a design, the vectorised skin readout,
probing scenes and the board's sensor model. May import `skin`, `robot`, `design`."""
