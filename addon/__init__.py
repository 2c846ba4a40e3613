"""skinsafe.addon."""
