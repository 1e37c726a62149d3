"""benchmarks.report_file: every benchmark report names the CPU it ran on and records what it read."""

from __future__ import annotations

import json

from benchmarks.report_file import write_report
from models.offline.host import host
from models.offline.provenance import file_input, file_sha256


def test_a_report_names_its_host_and_its_inputs(tmp_path):
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"not really a png")
    out = write_report(tmp_path / "bench" / "r.json", {"command": "python -m x"}, [file_input("image", photo)])
    doc = json.loads(out.read_text())
    assert doc["host"] == host() and doc["host"]["model"]
    assert doc["provenance"]["command"] == "python -m x"
    assert [(i["role"], i["sha256"]) for i in doc["provenance"]["inputs"]] == [("image", file_sha256(photo))]


def test_the_host_reads_the_model_name_and_the_isa_flags_that_matter(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(
        "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx2 fma avx512f avx512_vnni\n\n"
        "processor\t: 1\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx2 fma avx512f avx512_vnni\n"
    )
    assert host(cpuinfo) == {"model": "AMD EPYC 7B13", "isa": ["avx2", "fma", "avx512f", "avx512_vnni"]}
    avx2_only = tmp_path / "avx2"
    avx2_only.write_text("model name\t: AMD EPYC\nflags\t\t: fpu avx2 fma\n")
    assert host(avx2_only)["isa"] == ["avx2", "fma"]
    assert host(tmp_path / "missing")["isa"] is None
