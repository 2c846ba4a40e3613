"""The application: the `skinsafe` CLI, the demo, its report, `check` and the speed/accuracy trade
sweep. The composition root: the only part of core that may import `exporters` and `hardware`."""
