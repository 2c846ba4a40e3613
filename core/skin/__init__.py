"""The one artifact: the skin design (taxels as arrays, FPC modules, boards), board assignment,
the versioned taxel-map file and safe file writing. Imports numpy only."""
