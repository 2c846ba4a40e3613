"""skinsafe.core: the skin model, kinematics and the three safety layers (never imports bpy)."""
