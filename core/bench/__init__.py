"""`skinsafe bench NAME`: speed and accuracy against a simple reference in the same run.
May import the library layers; never `experiments` or `app`."""
