"""`skinsafe bench import`: the row keys are a contract; the built-in UR5 row meets the targets."""
from skinsafe.core.bench.robot_import import robot_row

KEYS = {"robot", "links", "triangles_in", "triangles_used", "import_s", "peak_mb", "taxel_to_surface_mm_worst",
        "taxel_to_collision_mm_worst", "contact_recall", "self_contacts_home"}


def test_ur5_row_has_the_contract_keys_and_meets_the_targets():
    row = robot_row("ur5", n_pokes=60, pitch=0.015)
    assert KEYS <= set(row)
    assert row["robot"] == "ur5" and row["links"] >= 3 and row["taxels"] > 100
    assert row["taxel_to_surface_mm_worst"] <= 1.0 and row["taxel_to_collision_mm_worst"] <= 1.0
    assert row["contact_recall"] >= 0.95 and row["self_contacts_home"] == 0
