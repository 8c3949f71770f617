"""Formats out (extended XYZ, GSD, VTU series) and in (GSD, extended XYZ, LAMMPS dump): round trips, what
the maintained readers see, and clear errors naming the file, frame and field."""

import json
import re

import numpy as np
import pytest

from dispgns.cli import main
from dispgns.data import DatasetError, DatasetMetadata, Trajectory, load_dataset, write_split
from dispgns.data.format import radii_groups, write_metadata
from dispgns.data.formats import export_trajectories, import_trajectory_files, read_lammps_dump
from dispgns.physics import PhysicsConfig

ase_io = pytest.importorskip("ase.io")
hoomd = pytest.importorskip("gsd.hoomd")
meshio = pytest.importorskip("meshio")

L = 0.1
RADII_M = [0.002, 0.0025, 0.004]


def _dataset(directory, dim, counts=(5, 7), n_frames=4, seed=0):
    rng = np.random.default_rng(seed)
    trajectories = []
    for n in counts:
        start = rng.uniform(-0.9, 0.9, (n, dim))
        position = start[None] + rng.normal(0, 1e-3, (n_frames, n, dim)).cumsum(0)
        position[0, 0, 0] = 1e-6  # a small coordinate: text formats must keep it to ~1e-8 m
        radius = rng.choice(RADII_M, n) / L
        trajectories.append(Trajectory(position=position.astype(np.float32), radius=radius.astype(np.float32)))
    directory.mkdir()
    write_split(directory / "test.h5", trajectories)
    write_metadata(
        directory,
        DatasetMetadata(
            dim=dim,
            sequence_length=n_frames,
            frame_dt=15e-4,
            save_every=15,
            box_half_size=L,
            connectivity_radius=0.2,
            trajectory_counts={"test": len(counts)},
            radii={"test": radii_groups([(len(counts), RADII_M)])},
            physics=PhysicsConfig().to_dict(),
            has_initial_state=False,
            particle_counts={"test": list(counts)},
        ),
    )
    return trajectories


@pytest.mark.parametrize("fmt", ["extxyz", "gsd"])
@pytest.mark.parametrize("dim", [2, 3])
def test_export_then_import_gives_the_same_arrays(tmp_path, fmt, dim):
    trajectories = _dataset(tmp_path / "data", dim)
    written = export_trajectories(tmp_path / "data", tmp_path / "out", fmt)
    assert [p.name for p in written] == [f"test_00000.{fmt}", f"test_00001.{fmt}"]
    info = json.loads((tmp_path / "out" / "export.json").read_text())
    assert info["length_unit"] == "m" and info["box_half_size_m"] == L and info["frame_dt_s"] == 15e-4
    metadata = import_trajectory_files(written, fmt, tmp_path / "back", split="test")
    assert (metadata.dim, metadata.box_half_size, metadata.frame_dt, metadata.save_every) == (dim, L, 15e-4, 15)
    _, read = load_dataset(tmp_path / "back")
    for got, want in zip(read["test"], trajectories):
        # Files hold metres (float32 in GSD, 8 decimals in XYZ): the normalised float32 values to ~1 ulp.
        np.testing.assert_allclose(got.position, want.position, atol=1.2e-7, rtol=0)
        np.testing.assert_array_equal(got.radius, want.radius)


def test_extended_xyz_reads_in_ase_as_ovito_reads_it(tmp_path):
    trajectories = _dataset(tmp_path / "data", 2)
    export_trajectories(tmp_path / "data", tmp_path / "out", "extxyz", indices=[1])
    frames = ase_io.read(tmp_path / "out" / "test_00001.extxyz", index=":", format="extxyz")
    want = trajectories[1]
    assert len(frames) == 4 and len(frames[0]) == 7
    for t, atoms in enumerate(frames):
        np.testing.assert_allclose(atoms.positions[:, :2], want.position[t] * L, atol=1e-8)
        assert np.all(atoms.positions[:, 2] == 0)
        assert atoms.info["Time"] == pytest.approx(t * 15e-4)
    np.testing.assert_allclose(frames[0].arrays["radius"], want.radius.astype(np.float64) * L, atol=1e-9)
    np.testing.assert_allclose(np.diag(frames[0].cell.array)[:2], [2 * L, 2 * L])
    np.testing.assert_allclose(frames[0].info["Origin"][:2], [-L, -L])
    assert not frames[0].pbc.any() and frames[0].info["length_unit"] == "m"


def test_gsd_holds_diameters_and_hoomds_box(tmp_path):
    trajectories = _dataset(tmp_path / "data", 2)
    export_trajectories(tmp_path / "data", tmp_path / "out", "gsd", indices=[0])
    with hoomd.open(str(tmp_path / "out" / "test_00000.gsd"), mode="r") as file:
        assert len(file) == 4
        frame = file[2]
        assert frame.configuration.dimensions == 2 and frame.configuration.step == 30
        np.testing.assert_allclose(frame.configuration.box, [2 * L, 2 * L, 0, 0, 0, 0], rtol=1e-7)
        np.testing.assert_allclose(frame.particles.diameter, 2 * trajectories[0].radius * L, rtol=1e-6)
        np.testing.assert_allclose(frame.particles.position[:, :2], trajectories[0].position[2] * L, rtol=1e-6)
        assert frame.log["dispgns/time_s"][0] == pytest.approx(30 * 1e-4)


def test_vtu_series_for_paraview(tmp_path):
    trajectories = _dataset(tmp_path / "data", 3)
    export_trajectories(tmp_path / "data", tmp_path / "out", "vtu", indices=[0])
    series = json.loads((tmp_path / "out" / "test_00000.vtu.series").read_text())
    assert series["file-series-version"] == "1.0"
    assert [f["name"] for f in series["files"]] == [f"test_00000_{t:05d}.vtu" for t in range(4)]
    mesh = meshio.read(tmp_path / "out" / series["files"][3]["name"])
    np.testing.assert_allclose(mesh.points, trajectories[0].position[3] * L, rtol=1e-6)
    np.testing.assert_allclose(mesh.point_data["radius"], trajectories[0].radius * L, rtol=1e-6)
    assert series["files"][3]["time"] == pytest.approx(3 * 15e-4)


def test_export_of_a_rollout_file_and_cli_rules(tmp_path, capsys):
    _dataset(tmp_path / "data", 2)
    # A split file alone (as dispgns evaluate writes predictions) needs the dataset's L and frame spacing.
    with pytest.raises(DatasetError, match="does not record L and the frame spacing"):
        export_trajectories(tmp_path / "data" / "test.h5", tmp_path / "out", "gsd")
    args = ["export", "gsd", str(tmp_path / "data" / "test.h5"), "--data", str(tmp_path / "data")]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    assert main([*args, "--out", str(tmp_path / "out")]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "out"), "--overwrite"]) == 0
    assert main(["export", "gsd", str(tmp_path / "data"), "--out", str(tmp_path / "o2"), "--index", "9"]) == 2
    assert "no index 9" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


DUMP = """ITEM: TIMESTEP
{step}
ITEM: NUMBER OF ATOMS
3
ITEM: BOX BOUNDS {box}
ITEM: ATOMS id type x y z diameter
{rows}
"""


def _dump(frames, box="ff ff ff\n0.0 200.0\n0.0 200.0\n-0.5 0.5"):
    text = ""
    for step, rows in frames:
        text += DUMP.format(step=step, box=box, rows="\n".join(" ".join(str(v) for v in row) for row in rows))
    return text


def test_lammps_dump_import_recentres_orders_by_id_and_needs_the_unit(tmp_path):
    # Millimetres, box [0, 200] mm: L = 0.1 m, centres re-centred on the box.
    frames = [
        (0, [(2, 1, 150.0, 100.0, 0.0, 5.0), (1, 1, 50.0, 60.0, 0.0, 4.0), (3, 1, 100.0, 20.0, 0.0, 8.0)]),
        (15, [(1, 1, 51.0, 59.0, 0.0, 4.0), (3, 1, 100.0, 19.0, 0.0, 8.0), (2, 1, 150.0, 99.0, 0.0, 5.0)]),
    ]
    path = tmp_path / "run.dump"
    path.write_text(_dump(frames))
    raw = read_lammps_dump(path)
    assert raw.length_unit is None and raw.position.shape == (2, 3, 3)
    with pytest.raises(DatasetError, match=r"run\.dump: the file does not state its length unit"):
        import_trajectory_files([path], "lammps-dump", tmp_path / "a")
    assert main(["import", "lammps-dump", str(path), "--out", str(tmp_path / "a"), "--length-unit", "1e-3"]) == 0
    metadata, read = load_dataset(tmp_path / "a")
    assert (
        metadata.dim == 2 and metadata.box_half_size == pytest.approx(L) and metadata.source == "imported lammps-dump"
    )
    trajectory = read["train"][0]
    np.testing.assert_allclose(trajectory.position[0], [[-0.5, -0.4], [0.5, 0.0], [0.0, -0.8]], atol=1e-7)
    np.testing.assert_allclose(trajectory.position[1, 0], [-0.49, -0.41], atol=1e-7)
    np.testing.assert_allclose(trajectory.radius, [0.02, 0.025, 0.04], rtol=1e-6)


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda f: f[1][1].pop(),
            r"run\.dump: frame 1: line \d+: expected 'ITEM: NUMBER OF ATOMS'|frame 1: 2 particles",
        ),
        (
            lambda f: f[1][1].__setitem__(0, (1, 1, float("nan"), 59.0, 0.0, 4.0)),
            r"frame 1: 'position' has a non-finite",
        ),
        (lambda f: f[1][1].__setitem__(0, (1, 1, 251.0, 59.0, 0.0, 4.0)), r"frame 1 particle 0: position axis 0"),
        (lambda f: f[1][1].__setitem__(0, (1, 1, 51.0, 59.0, 0.0, 6.0)), r"frame 1: 'radius' of particle 0"),
    ],
)
def test_lammps_dump_errors_name_file_frame_and_field(tmp_path, edit, message):
    frames = [
        (0, [(1, 1, 50.0, 60.0, 0.0, 4.0), (2, 1, 150.0, 100.0, 0.0, 5.0), (3, 1, 100.0, 20.0, 0.0, 8.0)]),
        (15, [(1, 1, 51.0, 59.0, 0.0, 4.0), (2, 1, 150.0, 99.0, 0.0, 5.0), (3, 1, 100.0, 19.0, 0.0, 8.0)]),
    ]
    edit(frames)
    text = _dump(frames)
    if len(frames[1][1]) == 2:  # the particle count changes: the header says 2
        text = text.replace("3\nITEM: BOX", "2\nITEM: BOX", 2).replace("2\nITEM: BOX", "3\nITEM: BOX", 1)
    path = tmp_path / "run.dump"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message):
        import_trajectory_files([path], "lammps-dump", tmp_path / "out", length_unit=1e-3)
    assert not (tmp_path / "out").exists()


def test_imports_check_times_and_missing_fields(tmp_path):
    _dataset(tmp_path / "data", 2)
    export_trajectories(tmp_path / "data", tmp_path / "out", "extxyz", indices=[0])
    path = tmp_path / "out" / "test_00000.extxyz"
    # The file's times (1.5 ms apart) disagree with save_every * dt = 1 ms.
    with pytest.raises(DatasetError, match=r"test_00000\.extxyz: frame 1: 'time' step is 0\.0015 s, expected 0\.001 s"):
        import_trajectory_files([path], "extxyz", tmp_path / "a", save_every=10)
    text = path.read_text().replace(":radius:R:1", "").replace("length_unit=m ", "")
    stripped = tmp_path / "plain.extxyz"
    stripped.write_text(
        "\n".join(" ".join(line.split()[:4]) if line.startswith("X") else line for line in text.splitlines())
    )
    with pytest.raises(DatasetError, match=r"plain\.extxyz: frame 0: no 'radius' or 'diameter' column"):
        import_trajectory_files([stripped], "extxyz", tmp_path / "b")


def _rectangular_dataset(directory, half, n_frames=4, count=5, seed=3):
    """A wide4-like dataset: the box's half-sizes ``half`` (m) per axis, positions and radii divided by L = 0.1 m
    (the vertical half-size), ``bounds`` = half / L."""
    rng = np.random.default_rng(seed)
    bounds = tuple((-float(f"{h / L:.12g}"), float(f"{h / L:.12g}")) for h in half)
    position = np.stack([rng.uniform(lo + 0.1, hi - 0.1, (n_frames, count)) for lo, hi in bounds], -1)
    trajectory = Trajectory(position=position.astype(np.float32), radius=np.full(count, 0.04, np.float32))
    directory.mkdir()
    write_split(directory / "test.h5", [trajectory], bounds=bounds)
    write_metadata(
        directory,
        DatasetMetadata(
            dim=len(half),
            sequence_length=n_frames,
            frame_dt=15e-4,
            save_every=15,
            box_half_size=half,
            length_scale=L,
            connectivity_radius=0.16,
            trajectory_counts={"test": 1},
            radii={"test": radii_groups([(1, [0.004])])},
            physics=PhysicsConfig(box_half_size=half).to_dict(),
            has_initial_state=False,
            particle_counts={"test": [count]},
        ),
    )
    return trajectory, bounds


@pytest.mark.parametrize("fmt", ["extxyz", "gsd"])
def test_export_of_a_rectangular_box_scales_by_the_length_scale_and_keeps_the_box(tmp_path, fmt):
    # A container four times wider than tall: positions are stored divided by L = 0.1 m, not by the box.
    half = (0.4, 0.1)
    trajectory, _ = _rectangular_dataset(tmp_path / "data", half)
    position = trajectory.position
    (written,) = export_trajectories(tmp_path / "data", tmp_path / "out", fmt)
    info = json.loads((tmp_path / "out" / "export.json").read_text())
    assert info["box_half_size_m"] == list(half) and info["length_scale_m"] == L
    if fmt == "extxyz":
        frames = ase_io.read(written, index=":")
        xy = np.stack([f.positions[:, :2] for f in frames])
        np.testing.assert_allclose(np.diag(frames[0].cell.array)[:2], [0.8, 0.2])
        np.testing.assert_allclose(frames[0].arrays["radius"], 0.004)
    else:
        with hoomd.open(str(written), "r") as file:
            xy = np.stack([f.particles.position[:, :2] for f in file])
            np.testing.assert_allclose(file[0].configuration.box[:2], [0.8, 0.2])
            np.testing.assert_allclose(file[0].particles.diameter, 0.008, rtol=1e-6)
    np.testing.assert_allclose(xy, position.astype(np.float64) * L, atol=1e-8)


@pytest.mark.parametrize("fmt", ["extxyz", "gsd"])
@pytest.mark.parametrize("half", [(0.4, 0.1), (0.3, 0.2, 0.1)])
def test_rectangular_box_export_then_import_gives_the_same_arrays_and_bounds(tmp_path, fmt, half):
    trajectory, bounds = _rectangular_dataset(tmp_path / "data", half)
    written = export_trajectories(tmp_path / "data", tmp_path / "out", fmt)
    metadata = import_trajectory_files(written, fmt, tmp_path / "back", split="test")
    # As generate --preset wide4 records the box: half-sizes per axis in m, L the vertical one, bounds h / L.
    assert metadata.box_half_size == half and metadata.length_scale == L
    assert metadata.bounds == bounds and metadata.physics_config.box_half_size == half
    assert metadata.connectivity_radius == pytest.approx(4 * 0.004 / L)
    back, read = load_dataset(tmp_path / "back")
    assert back.bounds == bounds and back.length_scale == L
    # One float32 rounding of the largest coordinate (|x| up to h / L = 4 here).
    np.testing.assert_allclose(read["test"][0].position, trajectory.position, atol=1.2e-7 * max(half) / L, rtol=0)
    np.testing.assert_array_equal(read["test"][0].radius, trajectory.radius)
    # A box given on the command line must agree with the file's.
    with pytest.raises(DatasetError, match=re.escape(f"'box' has half-sizes {list(half)} m, but [0.1, 0.1")):
        import_trajectory_files(written, fmt, tmp_path / "bad", box_half_size=0.1)
    assert not (tmp_path / "bad").exists()


def test_lammps_dump_with_a_rectangular_box_and_a_chosen_length_scale(tmp_path, capsys):
    # Millimetres, box [0, 800] x [0, 200] mm: half-sizes (0.4, 0.1) m; by default L = 0.1 m (the height).
    frames = [(0, [(1, 1, 50.0, 60.0, 0.0, 4.0), (2, 1, 750.0, 100.0, 0.0, 8.0), (3, 1, 400.0, 190.0, 0.0, 4.0)])]
    box = "ff ff ff\n0.0 800.0\n0.0 200.0\n-0.5 0.5"
    path = tmp_path / "wide.dump"
    path.write_text(_dump(frames, box=box))
    assert main(["import", "lammps-dump", str(path), "--out", str(tmp_path / "a"), "--length-unit", "1e-3"]) == 0
    assert "box half-size (0.4, 0.1) m, L = 0.1 m" in capsys.readouterr().out
    metadata, read = load_dataset(tmp_path / "a")
    assert metadata.box_half_size == (0.4, 0.1) and metadata.length_scale == 0.1
    assert metadata.bounds == ((-4.0, 4.0), (-1.0, 1.0))
    np.testing.assert_allclose(read["train"][0].position[0], [[-3.5, -0.4], [3.5, 0.0], [0.0, 0.9]], atol=1e-6)
    np.testing.assert_allclose(read["train"][0].radius, [0.02, 0.04, 0.02], rtol=1e-6)
    # --L chooses the length scale: positions, radii and bounds are in units of 0.2 m.
    args = ["import", "lammps-dump", str(path), "--out", str(tmp_path / "b"), "--length-unit", "1e-3", "--L", "0.2"]
    assert main(args) == 0
    metadata, read = load_dataset(tmp_path / "b")
    assert metadata.length_scale == 0.2 and metadata.bounds == ((-2.0, 2.0), (-0.5, 0.5))
    np.testing.assert_allclose(read["train"][0].position[0], [[-1.75, -0.2], [1.75, 0.0], [0.0, 0.45]], atol=1e-6)
    # A file without a box: --box gives it per axis (centred on 0).
    xyz = tmp_path / "nobox.extxyz"
    xyz.write_text("2\nProperties=species:S:1:pos:R:3:radius:R:1\nX -0.35 -0.04 0.0 0.002\nX 0.35 0.0 0.0 0.004\n")
    with pytest.raises(DatasetError, match=r"nobox\.extxyz: the file has no box; give its half-size"):
        import_trajectory_files([xyz], "extxyz", tmp_path / "c", length_unit=1.0)
    assert (
        main(["import", "extxyz", str(xyz), "--out", str(tmp_path / "c"), "--length-unit", "1", "--box", "0.4,0.1"])
        == 0
    )
    metadata, read = load_dataset(tmp_path / "c")
    assert metadata.box_half_size == (0.4, 0.1) and metadata.bounds == ((-4.0, 4.0), (-1.0, 1.0))
    np.testing.assert_allclose(read["train"][0].position[0], [[-3.5, -0.4], [3.5, 0.0]], atol=1e-6)


def test_tilted_boxes_are_refused_naming_the_file_and_field(tmp_path):
    frames = [(0, [(1, 1, 50.0, 60.0, 0.0, 4.0), (2, 1, 150.0, 100.0, 0.0, 8.0), (3, 1, 100.0, 20.0, 0.0, 8.0)])]
    path = tmp_path / "tilted.dump"
    path.write_text(_dump(frames, box="xy xz yz ff ff ff\n0.0 200.0 10.0\n0.0 200.0 0.0\n-0.5 0.5 0.0"))
    with pytest.raises(DatasetError, match=r"tilted\.dump: frame 0: 'ITEM: BOX BOUNDS' .*tilted \(triclinic\)"):
        import_trajectory_files([path], "lammps-dump", tmp_path / "a", length_unit=1e-3)

    snapshot = hoomd.Frame()
    snapshot.configuration.box = [0.2, 0.2, 0.2, 0.5, 0, 0]
    snapshot.particles.N = 1
    snapshot.particles.types = ["A"]
    snapshot.particles.position = np.zeros((1, 3), np.float32)
    snapshot.particles.diameter = np.full(1, 0.01, np.float32)
    with hoomd.open(name=str(tmp_path / "tilted.gsd"), mode="w") as file:
        file.append(snapshot)
    with pytest.raises(DatasetError, match=r"tilted\.gsd: frame 0: 'configuration/box' .*tilted \(triclinic\)"):
        import_trajectory_files([tmp_path / "tilted.gsd"], "gsd", tmp_path / "b", length_unit=1.0)

    xyz = tmp_path / "tilted.extxyz"
    xyz.write_text(
        '1\nLattice="0.2 0.0 0.0 0.05 0.2 0.0 0.0 0.0 0.2" Properties=species:S:1:pos:R:3:radius:R:1\n'
        "X 0.1 0.1 0.1 0.005\n"
    )
    with pytest.raises(DatasetError, match=r"tilted\.extxyz: frame 0: 'Lattice' .*tilted \(triclinic\)"):
        import_trajectory_files([xyz], "extxyz", tmp_path / "c", length_unit=1.0)
    assert not any((tmp_path / d).exists() for d in "abc")
