"""Series are listed, chosen and logged by salted hash: no UID or patient field reaches a log line, error or listing.

Every check runs the real ``ctsplat ingest`` command in a subprocess and greps its stdout and stderr (log lines,
warnings, errors, ``--list-series`` output) and the volume.json it writes for the identifying values read back
from the DICOM files with pydicom: on synthetic folders holding two series (one without a SeriesInstanceUID), and
on the real head CT in ../shared/data (skipped with a reason when absent).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
import pydicom.config
import pytest

from ctsplat.formats.sources import find_dicom_series, salted_hash, write_dicom_series

ROOT = Path(__file__).resolve().parents[2]

#: Header fields that identify a patient, a study or a site; none of their values may reach any output.
IDENTIFYING = (
    "SeriesInstanceUID", "StudyInstanceUID", "SOPInstanceUID", "FrameOfReferenceUID", "PatientName", "PatientID",
    "PatientBirthDate", "StudyDate", "SeriesDate", "AcquisitionDate", "ContentDate", "StudyTime", "SeriesTime",
    "InstitutionName", "InstitutionAddress", "ReferringPhysicianName", "AccessionNumber", "SeriesDescription",
)

ID_LINE = re.compile(r"^([0-9a-f]{16}) \(#")


def identifying_values(folder: Path) -> dict[str, str]:
    """value -> field name, for every identifying header value (4+ characters) of the DICOM files under ``folder``."""
    found: dict[str, str] = {}
    mode = pydicom.config.settings.reading_validation_mode
    pydicom.config.settings.reading_validation_mode = pydicom.config.IGNORE  # the planted invalid UIDs are fine here
    try:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            ds = pydicom.dcmread(path, stop_before_pixels=True)
            for key in IDENTIFYING:
                value = str(ds.get(key, "") or "").strip()
                if len(value) >= 4:
                    found.setdefault(value, key)
    finally:
        pydicom.config.settings.reading_validation_mode = mode
    return found


def assert_no_identifiers(text: str, values: dict[str, str]) -> None:
    leaks = sorted({f"{key}={value!r}" for value, key in values.items() if value in text})
    assert not leaks, f"identifying header values in the output: {leaks}\n{text}"


def ctsplat(*args: str | Path) -> subprocess.CompletedProcess:
    """Run ``ctsplat`` (debug logging on, so every log line is seen) as a real process."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from ctsplat.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, "-v", *map(str, args)], env=env, capture_output=True, text=True, timeout=300,
    )


def listed_ids(proc: subprocess.CompletedProcess) -> list[str]:
    ids = [m.group(1) for line in proc.stdout.splitlines() if (m := ID_LINE.match(line))]
    assert len(ids) == len(proc.stdout.splitlines()), proc.stdout
    return ids


# ------------------------------------------------------------------------------------------ two series in a folder


def write_two_series(folder: Path) -> dict[str, object]:
    """Series A (100 HU, a SeriesInstanceUID pydicom finds invalid) and B (500 HU, no SeriesInstanceUID at all),
    same size and SeriesNumber, in one folder, with patient, date and institution fields filled in."""
    shape = (8, 6, 5)
    common = dict(spacing_mm=(1.0, 1.0, 2.0), origin_lps=(0.0, 0.0, 0.0), patient_name="Doe^Jane Q",
                  patient_id="PID-4711-0815")
    a = write_dicom_series(np.full(shape, 100.0), folder, uid_seed="a", filename="a_{k:02d}.dcm", **common)
    b = write_dicom_series(np.full(shape, 500.0), folder, uid_seed="b", filename="b_{k:02d}.dcm", **common)
    uid_a = "1.2.826.0.1.3680043.8.498.0042.20240229"  # "0042": a leading zero, which pydicom warns about verbatim
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for path in a + b:
            ds = pydicom.dcmread(path)
            ds.StudyDate = ds.SeriesDate = ds.ContentDate = "19990314"
            ds.PatientBirthDate = "19450102"
            ds.InstitutionName = "St Example Hospital"
            ds.InstitutionAddress = "1 Example Road, Exampletown"
            ds.ReferringPhysicianName = "Who^Doctor"
            ds.AccessionNumber = "ACC-99887766"
            ds.SeriesDescription = "Doe Jane head 1945-01-02"  # free text: a technologist may type anything
            if path in a:
                ds.SeriesInstanceUID = uid_a
            else:
                del ds.SeriesInstanceUID
            ds.save_as(path)
    return {"uid_a": uid_a, "files_a": a, "files_b": b}


@pytest.fixture(scope="module")
def two_series(tmp_path_factory):
    folder = tmp_path_factory.mktemp("two") / "dicom"
    info = write_two_series(folder)
    return folder, info, identifying_values(folder)


def ingest_value(out: Path) -> tuple[float, dict]:
    """Median HU of a volume ingested with ``--intensity hu`` and its volume.json."""
    data = np.asarray(nib.load(out).dataobj)
    return float(np.median(data)), json.loads((out.parent / "volume.json").read_text())


def test_list_series_names_every_series_by_a_choosable_hash(two_series, tmp_path):
    folder, info, secrets = two_series
    proc = ctsplat("ingest", folder, "--list-series")
    assert proc.returncode == 0, proc.stderr
    ids = listed_ids(proc)
    assert len(ids) == 2 and len(set(ids)) == 2
    series = {s.uid: s for s in find_dicom_series(folder)}
    assert set(series) == {info["uid_a"], ""}
    id_a, id_b = salted_hash(info["uid_a"]), series[""].id
    assert set(ids) == {id_a, id_b}
    assert "no SeriesInstanceUID" in next(line for line in proc.stdout.splitlines() if line.startswith(id_b))
    assert "--series-uid ID" in proc.stderr
    assert_no_identifiers(proc.stdout + proc.stderr, secrets)

    # each listed id selects its series (B has no UID at all), and so does A's raw UID, the way it always could
    # and A's UID as a DICOM dump shows it, in brackets, or quoted with a final dot
    for selector, hu, sid in ((id_b, 500.0, id_b), (id_a, 100.0, id_a), (info["uid_a"], 100.0, id_a),
                              (f"[{info['uid_a']}]", 100.0, id_a), (f"'{info['uid_a']}.'", 100.0, id_a)):
        out = tmp_path / re.sub(r"\W", "_", selector) / "volume.nii.gz"
        proc = ctsplat("ingest", folder, out, "--series-uid", selector, "--grid", "8", "--intensity", "hu")
        assert proc.returncode == 0, proc.stderr
        value, meta = ingest_value(out)
        assert value == pytest.approx(hu, abs=1.0)
        assert meta["source"]["series_id"] == sid
        assert meta["source"]["series_uid_hash"] == (id_a if sid == id_a else None)
        assert_no_identifiers(proc.stdout + proc.stderr + (out.parent / "volume.json").read_text(), secrets)


def test_errors_about_series_name_them_by_hash_only(two_series, tmp_path):
    folder, info, secrets = two_series
    id_a = salted_hash(info["uid_a"])
    cases = [
        ((), "no unique largest one"),  # two series of equal size and no choice
        (("--series-uid", "1"), "series number '1' is ambiguous"),  # both are series #1
        (("--series-uid", "1.2.826.0.1.3680043.8.498.77"), "not found"),  # a UID of another scan: not echoed either
        (("--series-uid", "[1.2.826.0.1.3680043.8.498.77]"), "not found"),  # nor in a DICOM dump's brackets
        (("--series-uid", "0123456789abcdef"), "not found"),
    ]
    for args, match in cases:
        out = tmp_path / "out"
        proc = ctsplat("ingest", folder, out / "volume.nii.gz", "--grid", "8", *args)
        assert proc.returncode == 2, proc.stderr
        error = [line for line in proc.stderr.splitlines() if "error:" in line]
        assert len(error) == 1 and match in error[0], proc.stderr
        assert id_a in error[0]  # the listing that lets the user choose
        assert "1.2.826.0.1.3680043.8.498.77" not in proc.stderr
        assert not out.exists()
        assert_no_identifiers(proc.stdout + proc.stderr, secrets)


def test_largest_series_chosen_with_a_warning_naming_hashes(tmp_path):
    folder = tmp_path / "dicom"
    info = write_two_series(folder)
    info["files_b"][0].unlink()  # B now has 4 slices: A (5) is the unique largest
    secrets = identifying_values(folder)
    out = tmp_path / "v" / "volume.nii.gz"
    proc = ctsplat("ingest", folder, out, "--grid", "8", "--intensity", "hu")
    assert proc.returncode == 0, proc.stderr
    assert f"2 series in the input folder; using the largest CT one, {salted_hash(info['uid_a'])}" in proc.stderr
    assert str(folder) not in proc.stderr  # the log names no path: folders may be named after the patient
    assert ingest_value(out)[0] == pytest.approx(100.0, abs=1.0)
    assert_no_identifiers(proc.stdout + proc.stderr, secrets)


# ------------------------------------------------------------------------------------------ the real head CT


@pytest.fixture(scope="module")
def head_secrets(ct0051_head):
    values = identifying_values(ct0051_head)
    assert {"SeriesInstanceUID", "StudyInstanceUID", "PatientName", "PatientID", "PatientBirthDate"} <= set(
        values.values()
    ) and "20020604" in values  # the study date
    return values


def test_real_head_list_and_select_by_hash_or_uid_leak_nothing(ct0051_head, head_secrets, tmp_path):
    uid = str(pydicom.dcmread(next(ct0051_head.iterdir()), stop_before_pixels=True).SeriesInstanceUID)
    proc = ctsplat("ingest", ct0051_head, "--list-series")
    assert proc.returncode == 0, proc.stderr
    assert listed_ids(proc) == [salted_hash(uid)]
    assert "108 files" in proc.stdout
    texts = [proc.stdout + proc.stderr]
    for selector in (salted_hash(uid), uid):
        out = tmp_path / selector[:8] / "volume.nii.gz"
        proc = ctsplat("ingest", ct0051_head, out, "--series-uid", selector, "--grid", "16")
        assert proc.returncode == 0, proc.stderr
        meta = json.loads((out.parent / "volume.json").read_text())
        assert meta["source"]["series_id"] == meta["source"]["series_uid_hash"] == salted_hash(uid)
        assert meta["source"]["missing_slice_gaps"] == []  # the head's odd 1.0 mm step is no missing slice
        assert "SliceGapWarning" not in proc.stderr
        texts.append(proc.stdout + proc.stderr + (out.parent / "volume.json").read_text())
    proc = ctsplat("ingest", ct0051_head, tmp_path / "x" / "volume.nii.gz", "--series-uid", "7")
    assert proc.returncode == 2 and "not found" in proc.stderr and salted_hash(uid) in proc.stderr
    texts.append(proc.stdout + proc.stderr)
    for text in texts:
        assert_no_identifiers(text, head_secrets)


def test_real_head_with_missing_slices_warns_where_and_leaks_nothing(ct0051_head, head_secrets, tmp_path):
    """Slices 50..54 of the head removed (links to the other 103 files): a 9 mm hole in a 1.5 mm series."""
    by_z = sorted(
        ct0051_head.iterdir(),
        key=lambda p: float(pydicom.dcmread(p, stop_before_pixels=True).ImagePositionPatient[2]),
    )
    folder = tmp_path / "gappy"
    folder.mkdir()
    for k, path in enumerate(by_z):
        if not 50 <= k <= 54:
            (folder / path.name).symlink_to(path)
    out = tmp_path / "v" / "volume.nii.gz"
    proc = ctsplat("ingest", folder, out, "--grid", "16")
    assert proc.returncode == 0, proc.stderr
    gaps = json.loads((out.parent / "volume.json").read_text())["source"]["missing_slice_gaps"]
    assert len(gaps) == 1 and gaps[0]["gap_mm"] == 9.0 and gaps[0]["between_slices"] == [49, 50]
    assert gaps[0]["approx_missing_slices"] == 5
    lo, hi = gaps[0]["positions_mm"]
    warned = [line for line in proc.stderr.splitlines() if "9 mm between slices 49 and 50" in line]
    assert len(warned) == 1 and "WARNING" in warned[0]  # said once: the log, not the log and py.warnings
    assert all(f"at {lo:g} and {hi:g} mm along the slice normal" in line for line in warned)
    assert_no_identifiers(proc.stdout + proc.stderr + (out.parent / "volume.json").read_text(), head_secrets)


def test_a_series_number_selects_its_series_as_an_integer():
    """SeriesNumber is an integer (DICOM IS): ``2``, ``02`` and ``000002`` (as a scanner may write it) name the same
    series; a number no series has names none, and an id or UID wins over a number."""
    from ctsplat.formats.sources import SeriesInfo, select_series

    series = [SeriesInfo(uid="1.2.3", files=[], modality="CT", number="000002", id="00000000000000a2"),
              SeriesInfo(uid="1.2.4", files=[], modality="CT", number="7", id="00000000000000b7")]
    for selector in ("2", "02", "000002", " 2 "):
        assert [s.id for s in select_series(series, selector)] == ["00000000000000a2"]
    assert [s.id for s in select_series(series, "0007")] == ["00000000000000b7"]
    assert select_series(series, "3") == [] and select_series(series, "2.0") == []
    assert [s.id for s in select_series(series, "00000000000000B7")] == ["00000000000000b7"]
