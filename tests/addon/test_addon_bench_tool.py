"""`skinsafe bench design`'s Place Skin row: the real add-on in a fresh bpy process places one 8x8 module by a
ray and previews 50 mouse moves over the forearm (the figures are the bench's, not asserted here)."""
from skinsafe.core.bench.design import place_tool_row


def test_place_tool_row_places_a_module_and_times_every_move():
    row = place_tool_row()
    assert (row["tool"], row["module"], row["n_taxels"], row["modules"], row["moves"]) == \
        ("place_skin", "8x8", 64, 1, 50)
    assert 0 < row["preview_ms"] <= row["preview_ms_max"] and row["first_place_s"] > 0
    assert len(row["loadavg"]) == 3 and min(row["loadavg"]) >= 0  # the load it ran under, stated with the figures
