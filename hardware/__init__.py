"""skinsafe.hardware: the board wire protocol (PROTOCOL.md), host deploy and streaming over pyserial,
and a board emulator on pseudo-terminals. Imports numpy, pyserial and skinsafe.core's numpy-only
modules; never mujoco, torch or bpy."""
