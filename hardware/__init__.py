"""skinsafe.hardware."""
