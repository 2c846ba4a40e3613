"""The application: the `skinsafe` CLI, the demo, its report, `check` and the speed/accuracy trade
sweep. The composition root: the only part of core that may import `exporters`, and with the benches (core/bench:
serial and fault benches on emulated boards) the only part that imports `hardware`."""
