"""skinsafe.exporters."""
