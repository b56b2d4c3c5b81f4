"""The OpenSCENARIO step of ``omniscs bench dataset`` on two small variant stores and one the exporter refuses:
checker versions and issue counts, the round trip, the refusal reported (not fatal), its report part written."""
import pytest

from omniscs.bench.openscenario import ROUND_TRIP_M, write_openscenario_report
from tests.export.openscenario_fixtures import (adversarial_boxes, moving_track, source_scene, variant_store,
                                                variant_stores)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return source_scene(tmp_path_factory)


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    return variant_stores(tmp_path_factory)


def test_the_benchmark_step_reports_checker_versions_counts_and_the_round_trip(variants, scene, tmp_path):
    adversary = moving_track(scene)
    off = variant_store(scene, tmp_path / "off-v000", "off-v000", adversarial_boxes(scene, adversary, 30.0), None)
    result = write_openscenario_report(tmp_path / "reports", [*variants, off], tmp_path / "export")
    s = result["summary"]
    assert (s["variants"], s["refused"], s["xosc_files"], s["xodr_files"]) == (3, 1, 2, 1)
    assert s["files_passed"] == s["files"] == 3 and s["errors"] == 0
    assert s["asam-qc-opendrive version"] and s["asam-qc-openscenarioxml version"]
    assert s["round_trip_max_position_m"] < ROUND_TRIP_M
    assert not s["round_trip_holds"] and not s["all_passed"]  # the refused variant counts against the export
    refused = next(v for v in result["variants"] if v["store"] == "off-v000")
    assert "leaves the road network" in refused["refused"]
    report = tmp_path / "reports" / "dataset"
    assert sorted(p.name for p in report.iterdir()) == ["openscenario.json", "openscenario.md"]
    assert "| beh-v000 |" in (report / "openscenario.md").read_text()
    clean = write_openscenario_report(tmp_path / "reports", variants, tmp_path / "export")["summary"]
    assert clean["all_passed"] and clean["round_trip_holds"]


def test_the_round_trip_sees_a_moved_vertex(variants, tmp_path):
    """The round trip compares the file with the store's boxes: a vertex moved by 5 cm in the file is 5 cm off."""
    from omniscs.bench.openscenario import round_trip
    from omniscs.export import export_scenes

    out = export_scenes(variants[:1], "openscenario", tmp_path / "x")
    xosc = out / "beh-v000.xosc"
    assert round_trip(variants[0], xosc)["position_m"] < 1e-9
    text = xosc.read_text()
    i = text.index("<Vertex", text.index('name="ego_trajectory"'))
    j = text.index('x="', i) + 3
    k = text.index('"', j)
    xosc.write_text(text[:j] + repr(float(text[j:k]) + 0.05) + text[k:])
    assert abs(round_trip(variants[0], xosc)["position_m"] - 0.05) < 1e-9
