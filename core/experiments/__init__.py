"""The paper's experiments (maze, tracking, desk, collaboration, poke), each a `skinsafe
experiment` / command module. May import the library layers; never `bench` or `app`."""
