"""`skinsafe bench NAME`: speed and accuracy against a simple reference in the same run.
May import the library layers and `hardware` (the serial and fault benches drive emulated boards); never
`experiments`, `app`, exporters or the add-on (import-linter). A bench that measures a whole command runs the
product as a user does, through its `skinsafe` command (core/system.SKINSAFE), never by an app module's name."""
