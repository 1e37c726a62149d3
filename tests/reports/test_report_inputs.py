"""No committed report is stale: every input a report recorded (its SHA-256 under `provenance`) still hashes the
same. Inputs in the repository are checked everywhere; the licensed sources under ../shared where ../shared is
present; built files (data/, artifacts/) are recorded only (models/offline/provenance.py says why). Reports
written before the rule are listed in reports/PREDATING.txt and must not grow in number. The int8 backbone is
made on each machine from code (its recipe), so a report on its features records the recipe's fingerprint, and a
changed recipe makes the report stale here too."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from models.offline.provenance import check_record, records

ROOT = Path(__file__).resolve().parents[2]
REPORTS = ROOT / "reports"
PREDATING = REPORTS / "PREDATING.txt"


def predating() -> set[str]:
    lines = PREDATING.read_text().splitlines()
    return {ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")}


def report_files() -> list[Path]:
    return sorted(REPORTS.rglob("*.json"))


def recorded() -> list[tuple[str, str, dict]]:
    out = []
    for path in report_files():
        for where, record in records(json.loads(path.read_text())):
            out.append((path.relative_to(ROOT).as_posix(), where, record))
    return out


def feature_records(doc: object, where: str = "") -> list[tuple[str, dict]]:
    """Every record of the features a report read (a mapping naming `backbone` and `backbone_dim`)."""
    found: list[tuple[str, dict]] = []
    if isinstance(doc, dict):
        if "backbone" in doc and "backbone_dim" in doc:
            found.append((where or "/", doc))
        for key, value in doc.items():
            found.extend(feature_records(value, f"{where}/{key}"))
    elif isinstance(doc, list):
        for k, value in enumerate(doc):
            found.extend(feature_records(value, f"{where}/{k}"))
    return found


def test_every_report_on_int8_features_names_the_recipe_the_code_makes_now():
    from models.offline.backbones.cnn import file_fingerprint
    from models.offline.backbones.efficientnet import efficientnet_lite0_weights_path
    from models.offline.backbones.quantize import INT8_SUFFIX, int8_fingerprint

    now = int8_fingerprint(file_fingerprint(efficientnet_lite0_weights_path()))
    int8_reports, stale = 0, []
    for path in report_files():
        for where, features in feature_records(json.loads(path.read_text())):
            if not str(features["backbone"]).endswith(INT8_SUFFIX):
                continue
            int8_reports += 1
            if features.get("backbone_fingerprint") != now:
                stale.append(f"{path.relative_to(ROOT)} ({where}): {features.get('backbone_fingerprint')}")
    assert int8_reports, "no committed report reads int8 features: the served configuration's reports are gone"
    assert not stale, f"reports made from int8 features of another recipe than today's ({now}): {stale}"


def test_every_report_records_its_inputs_or_predates_the_rule():
    listed = predating()
    gone = sorted(p for p in listed if not (ROOT / p).is_file())
    assert not gone, f"reports/PREDATING.txt lists files that do not exist: {gone}"
    missing = []
    for path in report_files():
        rel = path.relative_to(ROOT).as_posix()
        if rel not in listed and not records(json.loads(path.read_text())):
            missing.append(rel)
    assert not missing, (
        f"reports without a `provenance` record (write them with models.offline.provenance, or "
        f"benchmarks.report_file.write_report): {missing}"
    )


@pytest.mark.parametrize("report, where, record", recorded(), ids=lambda v: v if isinstance(v, str) else "")
def test_no_committed_report_has_stale_inputs(report, where, record):
    stale = [c for c in check_record(record) if c.status in ("changed", "missing")]
    assert not stale, (
        f"{report} ({where}) was made from inputs that have changed since: "
        + "; ".join(f"{c.path} {c.status} ({c.why})" for c in stale)
        + f". Regenerate it: {record.get('command') or 'reports/regenerate.sh'}"
    )
    assert record["commit"] is None or len(record["commit"]) == 40
