"""``slipfleet import`` reading logs: the column mapping, ISO times, Parquet, topic choice, the
dry run's summary and the one-line error naming the first bad row or message."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from server.cli import main
from server.tooling.importer import read_log
from server.tooling.importer_bags import TopicChoice
from server.tooling.importer_log import LogError, packets_of

T0 = 1_780_000_000_000_000_000
HEADER = (
    "stream,stamp_ns,accel_x_mps2,accel_y_mps2,accel_z_mps2,gyro_x_radps,gyro_y_radps,gyro_z_radps"
)


def _imu_rows(n: int, accel_x: str = "0.1") -> list[str]:
    return [f"imu,{T0 + i * 10_000_000},{accel_x},0.2,9.81,0.0,0.0,0.01" for i in range(n)]


def _csv(tmp_path: Path, lines: list[str], name: str = "log.csv") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _one_line_error(args: list[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(args)
    text = str(exc.value.code)
    assert "\n" not in text
    return text


def test_csv_samples_become_batched_packets(tmp_path: Path) -> None:
    gnss = f"gnss,{T0 + 5_000_000},,,,,,,52.0,5.6,40.0,1.0,0.5,0.0,,"
    header = HEADER + ",lat_deg,lon_deg,height_m,vel_east_mps,vel_north_mps,vel_up_mps,fix,"
    lines = [header + "omega_left_radps"]
    lines += [row + "," * 8 for row in _imu_rows(25)] + [gnss]
    log = read_log(_csv(tmp_path, lines), "csv", None, TopicChoice())
    assert log.counts() == {"imu": 25, "gnss": 1}
    g = log.gnss[0]
    assert (g.lat_deg, g.vel_enu_mps, int(g.fix)) == (52.0, (1.0, 0.5, 0.0), 4)
    assert math.isnan(g.heading_rad) and math.isnan(g.vel_std_mps)
    packets = packets_of(log, "v1")
    assert [p.stream.value for p in packets] == ["gnss", "imu", "imu", "imu"]
    assert [p.last_stamp_ns - T0 for p in packets] == [5e6, 90e6, 190e6, 240e6]


def test_a_value_that_is_no_number_is_named_by_row_and_column(tmp_path: Path) -> None:
    rows = _imu_rows(5)
    rows[2] = rows[2].replace("0.1", "abc", 1)
    path = _csv(tmp_path, [HEADER, *rows])
    text = _one_line_error(["import", str(path), "--vehicle", "v1", "--dry-run"])
    assert text.endswith("row 3: accel_x_mps2 'abc' is not a number"), text


def test_a_sample_the_server_would_refuse_is_named_with_the_reason(tmp_path: Path) -> None:
    rows = _imu_rows(12)
    rows[6] = rows[6].replace("0.1", "5000", 1)  # beyond the protocol's accelerometer range
    path = _csv(tmp_path, [HEADER, *rows])
    text = _one_line_error(["import", str(path), "--vehicle", "v1", "--dry-run"])
    assert "row 7: imu sample refused (out_of_range" in text, text


def test_a_repeated_stamp_names_both_rows(tmp_path: Path) -> None:
    rows = _imu_rows(4)
    rows[3] = rows[3].replace(str(T0 + 30_000_000), str(T0 + 20_000_000))
    with pytest.raises(LogError, match="row 4: IMU stamp repeats that of row 3"):
        read_log(_csv(tmp_path, [HEADER, *rows]), "csv", None, TopicChoice())


def test_a_column_map_renames_columns_and_streams_and_iso_times_are_read(tmp_path: Path) -> None:
    lines = ["kind,t,ax,ay,az,gx,gy,gz"]
    lines += [f"IMU,2026-06-01T12:00:00.{i:02d}0000001+02:00,0.1,0.2,9.8,0,0,0" for i in range(3)]
    cmap = tmp_path / "map.toml"
    cmap.write_text(
        '[columns]\nstream = "kind"\ntime = "t"\naccel_x_mps2 = "ax"\naccel_y_mps2 = "ay"\n'
        'accel_z_mps2 = "az"\ngyro_x_radps = "gx"\ngyro_y_radps = "gy"\ngyro_z_radps = "gz"\n'
        '[streams]\nimu = "IMU"\n'
    )
    log = read_log(_csv(tmp_path, lines), "csv", cmap, TopicChoice())
    first = 1_780_308_000_000_000_001  # 2026-06-01T10:00:00.000000001Z
    assert log.imu.stamp_ns.tolist() == [first, first + 10_000_000, first + 20_000_000]
    assert log.imu.accel_mps2[0].tolist() == [0.1, 0.2, 9.8]


def test_an_unknown_stream_is_named(tmp_path: Path) -> None:
    path = _csv(tmp_path, [HEADER, *_imu_rows(2), "lidar,1,,,,,,"])
    with pytest.raises(LogError, match="row 3: stream 'lidar' is not one of"):
        read_log(path, "csv", None, TopicChoice())


def test_parquet_with_typed_columns(tmp_path: Path) -> None:
    table = pa.table(
        {
            "stream": ["wheels", "wheels"],
            "stamp_ns": pa.array([T0, T0 + 20_000_000], pa.int64()),
            "omega_left_radps": [1.5, 1.6],
            "omega_right_radps": [1.4, None],
        }
    )
    path = tmp_path / "log.parquet"
    pq.write_table(table, path)
    with pytest.raises(LogError, match="row 2: omega_right_radps is empty"):
        read_log(path, "parquet", None, TopicChoice())


def test_dry_run_summarises_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("SLIPFLEET_STORAGE__DATA_DIR", str(tmp_path / "data"))
    path = _csv(tmp_path, [HEADER, *_imu_rows(30)])
    assert main(["import", str(path), "--vehicle", "v1", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "v1: 3 packets from 2026-05-28T" in out and "(0.3 s)" in out, out
    assert out.splitlines()[1].split() == ["imu", "30", "samples", "3", "packets"], out
    assert not (tmp_path / "data").exists()


def test_an_mcap_with_two_imu_topics_asks_which(tmp_path: Path) -> None:
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "two.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="tests")
        text, _ = ts.generate_msgdef("sensor_msgs/msg/Imu", ros_version=2)
        schema = w.register_schema("sensor_msgs/msg/Imu", "ros2msg", text.encode())
        for topic in ("/imu/a", "/imu/b"):
            w.register_channel(topic, "cdr", schema)
        w.finish()
    with pytest.raises(LogError, match=r"2 imu topics \(/imu/a, /imu/b\): choose one with"):
        read_log(path, "mcap", None, TopicChoice())
    assert read_log(path, "mcap", None, TopicChoice(imu="/imu/b")).counts() == {}


def test_a_ros1_bag_reads_imu_in_the_product_frame_and_wheel_joints_by_name(
    tmp_path: Path,
) -> None:
    import numpy as np
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    vec = T["geometry_msgs/msg/Vector3"]

    def header(k: int) -> Any:
        stamp = T0 + k * 10_000_000
        time = T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return T["std_msgs/msg/Header"](seq=k, stamp=time, frame_id="base_link")

    path = tmp_path / "old.bag"
    with Writer(path) as w:
        imu = w.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=ts)
        joints = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        for k in range(3):
            msg = T["sensor_msgs/msg/Imu"](
                header=header(k),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=vec(x=0.01, y=0.02, z=0.3),  # ROS: x forward, y left
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vec(x=1.0, y=-0.5, z=9.8),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(imu, T0 + k, ts.serialize_ros1(msg, "sensor_msgs/msg/Imu"))
            js = T["sensor_msgs/msg/JointState"](
                header=header(k),
                name=["steer", "wheel_r", "wheel_l"],
                position=np.zeros(3),
                velocity=np.array([9.0, 2.0 + k, 1.0 + k]),
                effort=np.zeros(0),
            )
            w.write(joints, T0 + k, ts.serialize_ros1(js, "sensor_msgs/msg/JointState"))
    choice = TopicChoice(wheel_joints=("wheel_l", "wheel_r"))
    log = read_log(path, "rosbag", None, choice)
    assert log.imu.stamp_ns.tolist() == [T0, T0 + 10_000_000, T0 + 20_000_000]
    assert log.imu.accel_mps2[0].tolist() == [0.5, 1.0, 9.8]  # X right, Y forward, Z up
    assert log.imu.gyro_radps[0].tolist() == [-0.02, 0.01, 0.3]
    assert log.wheels.omega_radps.tolist() == [[1.0, 2.0], [2.0, 3.0], [3.0, 4.0]]
    with pytest.raises(LogError, match=r"message \d on /joint_states: no left and right wheel"):
        read_log(path, "rosbag", None, TopicChoice())


def _import_csv(path: Path, monkeypatch: pytest.MonkeyPatch, **env: str) -> int:
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return main(["import", str(path), "--vehicle", "csv-drive"])


def _stored_rows(**storage: Any) -> Any:
    from server.settings import Settings
    from server.storage import open_store

    store = open_store(Settings(storage=storage).storage)
    try:
        return store.query_series("csv-drive", 0, 2**62)
    finally:
        store.close()


@pytest.mark.postgres
def test_import_into_postgresql_matches_sqlite_and_a_second_import_adds_nothing(
    tmp_path: Path, pg_database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    import time

    import numpy as np

    from tests.server.tooling.import_drive import make_drive, write_csv

    path = tmp_path / "drive.csv"
    write_csv(make_drive(time.time_ns() - 600 * 10**9), path)
    sqlite_dir = str(tmp_path / "sqlite")
    assert _import_csv(path, monkeypatch, SLIPFLEET_STORAGE__DATA_DIR=sqlite_dir) == 0
    assert _import_csv(path, monkeypatch, SLIPFLEET_STORAGE__URL=pg_database_url) == 0
    on_sqlite = _stored_rows(data_dir=sqlite_dir)
    on_pg = _stored_rows(url=pg_database_url)
    assert len(on_pg) == len(on_sqlite) > 300
    for name in on_sqlite.dtype.names:
        np.testing.assert_allclose(on_pg[name], on_sqlite[name], rtol=1e-9, err_msg=name)
    # the same log again: its estimates are those already stored, which the store keeps once
    assert _import_csv(path, monkeypatch, SLIPFLEET_STORAGE__URL=pg_database_url) == 0
    assert len(_stored_rows(url=pg_database_url)) == len(on_pg)
