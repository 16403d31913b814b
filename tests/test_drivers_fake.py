# The fakes copy the libraries' own names (camelCase methods, lower-case classes).
# ruff: noqa: N801, N802, N818
"""Live camera drivers against fake device libraries that mimic each library's API.

The fakes are injected as modules in ``sys.modules`` (as the real import would find
them), so no hardware and no driver package is needed.
"""

from __future__ import annotations

import enum
import sys
import types

import numpy as np
import pytest

from gaitflow.camera import Camera
from gaitflow.drivers import (
    CameraDriver,
    K4ADriver,
    Kinect2Driver,
    RealSenseDriver,
    fit_brown_conrady,
    ir8_to_u16,
    make_driver,
)
from gaitflow.errors import DriverError

# --------------------------------------------------------------------------- pylibfreenect2


def fake_freenect2(n_frames: int = 3, devices: int = 1, timeouts: int = 0) -> types.ModuleType:
    """A pylibfreenect2 look-alike: Freenect2, SyncMultiFrameListener, FrameType, pipelines."""
    mod = types.ModuleType("pylibfreenect2")
    log: list[str] = []
    mod.log = log

    class FrameType(enum.IntFlag):
        Color = 1
        Ir = 2
        Depth = 4

    class Frame:
        def __init__(self, arr, ts):
            self._a, self.timestamp = arr, ts

        def asarray(self, dtype=None):
            assert dtype is np.float32
            return self._a  # a view of the device buffer, as the real one

    class Listener:
        def __init__(self, types_):
            assert types_ == FrameType.Ir | FrameType.Depth
            self.n, self.waits = 0, 0
            self.released = 0

        def waitForNewFrame(self, frame_map=None, milliseconds=-1):
            self.waits += 1
            if self.waits <= timeouts:
                return None
            if self.n >= n_frames:
                return None
            i = self.n
            self.n += 1
            ir = np.full((424, 512), 1000.0 * (i + 1), np.float32)
            ir[0, 0] = 70000.0  # above range: saturates
            ir[0, 1] = 12.6
            depth = np.full((424, 512), 2500.4, np.float32)
            depth[0, 0] = 0.0
            depth[0, 1] = np.nan
            # The 32-bit tick wraps between frames 1 and 2.
            ticks = [2**32 - 334, 2**32 - 1, 332]
            return {"ir": Frame(ir, ticks[i % 3]), "depth": Frame(depth, ticks[i % 3])}

        def release(self, frame_map):
            self.released += 1

    class Params:
        fx, fy, cx, cy = 365.1, 365.2, 257.3, 204.9
        k1, k2, k3, p1, p2 = 0.091, -0.27, 0.094, 0.001, -0.002

    class Device:
        def setIrAndDepthFrameListener(self, listener):
            self.listener = listener

        def startStreams(self, rgb, depth):
            assert rgb is False and depth is True
            log.append("start")

        def getIrCameraParams(self):
            assert "start" in log  # the real parameters exist only once streaming
            return Params()

        def stop(self):
            log.append("stop")

        def close(self):
            log.append("close")

    class Freenect2:
        def enumerateDevices(self):
            return devices

        def getDeviceSerialNumber(self, i):
            return "0123456789"

        def openDevice(self, serial, pipeline=None):
            assert isinstance(pipeline, CpuPacketPipeline)
            log.append(f"open {serial}")
            return Device()

    class CpuPacketPipeline:
        pass

    mod.FrameType, mod.Freenect2 = FrameType, Freenect2
    mod.SyncMultiFrameListener = Listener
    mod.CpuPacketPipeline = CpuPacketPipeline  # no OpenGL/OpenCL on this "machine"
    return mod


def test_kinect2_reads_intrinsics_and_converts_frames(monkeypatch):
    fake = fake_freenect2()
    monkeypatch.setitem(sys.modules, "pylibfreenect2", fake)
    d = make_driver("kinect2", timeout_ms=10)
    assert isinstance(d, CameraDriver)
    d.open()
    doc = d.intrinsics()
    cam = Camera.from_json(doc)  # a valid camera.json document
    assert (cam.width, cam.height, cam.model) == (512, 424, "kinect-v2")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (365.1, 365.2, 257.3, 204.9)
    assert (cam.k1, cam.k2, cam.k3, cam.p1, cam.p2) == (0.091, -0.27, 0.094, 0.001, -0.002)
    assert doc["serial"] == "0123456789" and doc["driver"] == "kinect2"
    got = []
    it = d.frames()
    for _ in range(3):
        got.append(next(it))
    ts = [g[0] for g in got]
    assert ts[1] - ts[0] == 333 * 100_000  # 0.1 ms ticks
    assert ts[2] - ts[1] == 333 * 100_000  # unwrapped across the uint32 wrap
    _, ir, depth = got[0]
    assert ir.dtype == np.uint16 and depth.dtype == np.uint16 and ir.shape == (424, 512)
    assert ir[0, 0] == 65535 and ir[0, 1] == 13 and ir[5, 5] == 1000
    assert depth[0, 0] == 0 and depth[0, 1] == 0 and depth[5, 5] == 2500
    assert d._listener.released == 3  # every frame map handed back to libfreenect2
    d.close()
    d.close()  # idempotent
    assert fake.log == ["open 0123456789", "start", "stop", "close"]


def test_kinect2_no_device_and_timeouts(monkeypatch):
    monkeypatch.setitem(sys.modules, "pylibfreenect2", fake_freenect2(devices=0))
    with pytest.raises(DriverError, match="no Kinect v2 found"):
        Kinect2Driver().open()
    monkeypatch.setitem(sys.modules, "pylibfreenect2", fake_freenect2(n_frames=0))
    d = Kinect2Driver(timeout_ms=5, max_timeouts=3)
    d.open()
    with pytest.raises(DriverError, match=r"no frame for 3 x 5 ms"):
        next(d.frames())
    assert d.timeouts == 3


def test_kinect2_survives_a_few_timeouts(monkeypatch):
    monkeypatch.setitem(sys.modules, "pylibfreenect2", fake_freenect2(n_frames=1, timeouts=2))
    d = Kinect2Driver(timeout_ms=5, max_timeouts=3)
    d.open()
    _, ir, _ = next(d.frames())
    assert d.timeouts == 2 and d.frames_delivered == 1 and ir[5, 5] == 1000


# --------------------------------------------------------------------------- pyk4a


def fake_pyk4a(shape=(576, 640), n_missing: int = 0, n_calls: int = 100) -> types.ModuleType:
    mod = types.ModuleType("pyk4a")
    state = {"started": False, "stopped": False, "calls": 0, "config": None}
    mod.state = state

    class ColorResolution(enum.IntEnum):
        OFF = 0
        RES_720P = 1

    class DepthMode(enum.IntEnum):
        OFF = 0
        NFOV_2X2BINNED = 1
        NFOV_UNBINNED = 2
        WFOV_2X2BINNED = 3
        WFOV_UNBINNED = 4

    class FPS(enum.IntEnum):
        FPS_5 = 0
        FPS_15 = 1
        FPS_30 = 2

    class CalibrationType(enum.IntEnum):
        DEPTH = 0
        COLOR = 1

    class K4AException(Exception):
        pass

    class K4ATimeoutException(K4AException):
        pass

    class Config:
        def __init__(self, **kw):
            self.kw = kw

    class Calibration:
        def get_camera_matrix(self, camera):
            assert camera == CalibrationType.DEPTH
            return np.array([[504.0, 0, 321.5], [0, 504.1, 330.2], [0, 0, 1]])

        def get_distortion_coefficients(self, camera):
            assert camera == CalibrationType.DEPTH
            # Real Azure Kinect depth values: k1, k2, p1, p2, k3, k4, k5, k6.
            return np.array([3.13, 2.32, 8.1e-5, -5.1e-5, 0.130, 3.46, 3.35, 0.663])

    class Capture:
        def __init__(self, i):
            bad = i < n_missing
            self.ir = None if bad else np.full(shape, 100 + i, np.uint16)
            self.depth = None if bad else np.full(shape, 1800, np.uint16)
            self.depth_timestamp_usec = 1_000_000 + i * 33_333

    class PyK4A:
        def __init__(self, config, device_id=0):
            state["config"] = config.kw

        def start(self):
            state["started"] = True

        def stop(self):
            state["stopped"] = True

        @property
        def calibration(self):
            return Calibration()

        def get_capture(self, timeout=-1):
            state["calls"] += 1
            if state["calls"] == 2 or state["calls"] > n_calls:
                raise K4ATimeoutException("timeout")
            return Capture(state["calls"] - 1)

    for name, obj in list(locals().items()):
        if isinstance(obj, type):
            setattr(mod, name, obj)
    return mod


def test_k4a_reads_intrinsics_and_refits_distortion(monkeypatch):
    fake = fake_pyk4a()
    monkeypatch.setitem(sys.modules, "pyk4a", fake)
    d = K4ADriver(timeout_ms=10)
    d.open()
    cfg = fake.state["config"]
    assert cfg["color_resolution"] == fake.ColorResolution.OFF
    assert cfg["depth_mode"] == fake.DepthMode.NFOV_UNBINNED
    assert cfg["camera_fps"] == fake.FPS.FPS_30 and cfg["synchronized_images_only"] is False
    doc = d.intrinsics()
    cam = Camera.from_json(doc)
    assert (cam.width, cam.height) == (640, 576)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (504.0, 504.1, 321.5, 330.2)
    assert doc["rational_distortion"][5] == pytest.approx(3.46)
    # The refitted Brown-Conrady model reproduces the rational one across the image.
    assert doc["distortion_fit_rms_px"] < 0.5
    frames = d.frames()
    ts0, ir0, depth0 = next(frames)
    ts2, ir2, _ = next(frames)  # the timeout on the 2nd call is survived
    assert ts0 == 1_000_000_000 and ts2 - ts0 == 2 * 33_333_000
    assert ir0.dtype == np.uint16 and ir0[0, 0] == 100 and depth0[0, 0] == 1800
    assert ir2[0, 0] == 102 and d.timeouts == 1
    d.close()
    assert fake.state["stopped"]


def test_k4a_counts_captures_without_images_and_wrong_sizes(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyk4a", fake_pyk4a(n_missing=1))
    d = K4ADriver()
    d.open()
    next(d.frames())
    assert d.frames_bad == 1 and d.frames_delivered == 1
    # Captures of the wrong size are dropped and counted; then the camera goes quiet.
    monkeypatch.setitem(sys.modules, "pyk4a", fake_pyk4a(shape=(10, 10), n_calls=4))
    d = K4ADriver(max_timeouts=2)
    d.open()
    with pytest.raises(DriverError, match="no frame for 2 x"):
        next(d.frames())
    assert d.frames_bad == 3 and d.frames_delivered == 0 and d.timeouts == 3


def test_k4a_rejects_unknown_mode():
    with pytest.raises(DriverError, match="depth_mode 'HUGE'"):
        K4ADriver(depth_mode="HUGE")
    with pytest.raises(DriverError, match="fps 60"):
        K4ADriver(fps=60)


def test_fit_brown_conrady_matches_camera_model():
    coeffs = [0.5, -0.2, 1e-3, -2e-3, 0.05, 0.4, -0.1, 0.02]
    fx, fy, cx, cy, w, h = 500.0, 500.0, 320.0, 288.0, 640, 576
    dist, rms = fit_brown_conrady(coeffs, fx, fy, cx, cy, w, h)
    cam = Camera(width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy, **dist)
    # Compare the fitted model with the rational one at points inside the field.
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.5, 0.5, 200)
    y = rng.uniform(-0.45, 0.45, 200)
    k1, k2, p1, p2, k3, k4, k5, k6 = coeffs
    r2 = x * x + y * y
    rad = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    u = fx * (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)) + cx
    v = fy * (y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y) + cy
    got = cam.project(np.stack([x, y, np.ones_like(x)], axis=1))
    err = np.hypot(got[:, 0] - u, got[:, 1] - v)
    assert rms < 0.5 and err.max() < 2.0
    # Without a denominator the coefficients pass through unchanged.
    plain, rms0 = fit_brown_conrady([0.1, -0.2, 0.0, 0.0, 0.05], fx, fy, cx, cy, w, h)
    assert plain == {"k1": 0.1, "k2": -0.2, "k3": 0.05, "p1": 0.0, "p2": 0.0} and rms0 == 0.0


# --------------------------------------------------------------------------- pyrealsense2


def fake_realsense(scale: float = 0.001, model: str = "brown_conrady", coeffs=None):
    rs = types.ModuleType("pyrealsense2")
    calls: list[tuple] = []
    rs.calls = calls

    class stream(enum.Enum):
        depth = 1
        infrared = 2

    class format(enum.Enum):
        z16 = 1
        y8 = 2

    class distortion(enum.Enum):
        none = 0
        brown_conrady = 1
        inverse_brown_conrady = 2
        modified_brown_conrady = 3

    class Intrinsics:
        width, height = 848, 480
        fx, fy, ppx, ppy = 421.0, 421.5, 425.1, 238.7

    intr = Intrinsics()
    intr.model = getattr(distortion, model)
    intr.coeffs = coeffs if coeffs is not None else [0.0] * 5

    class VideoProfile:
        def get_intrinsics(self):
            return intr

    class StreamProfile:
        def as_video_stream_profile(self):
            return VideoProfile()

    class Sensor:
        def get_depth_scale(self):
            return scale

    class Device:
        def first_depth_sensor(self):
            return Sensor()

    class Profile:
        def get_stream(self, s):
            assert s == stream.depth
            return StreamProfile()

        def get_device(self):
            return Device()

    class Data:
        def __init__(self, a):
            self.a = a

        def get_data(self):
            return self.a

    class FrameSet:
        def __init__(self, i):
            self.i = i

        def get_depth_frame(self):
            d = np.full((480, 848), 1000, np.uint16)
            d[0, 0] = 0
            return Data(d)

        def get_infrared_frame(self, index):
            assert index == 1  # the left imager: the one depth is computed in
            ir = np.full((480, 848), 128, np.uint8)
            ir[0, 0] = 255
            return Data(ir)

        def get_timestamp(self):
            return 1234.5 + self.i * 33.3333

    class config:
        def enable_stream(self, *args):
            calls.append(args)

        def enable_device(self, serial):
            calls.append(("device", serial))

    class pipeline:
        def __init__(self):
            self.i = 0

        def start(self, cfg):
            return Profile()

        def wait_for_frames(self, timeout_ms=5000):
            self.i += 1
            if self.i == 2:
                raise RuntimeError("Frame didn't arrive within 5000")
            return FrameSet(self.i)

        def stop(self):
            calls.append(("stop",))

    for name, obj in list(locals().items()):
        if isinstance(obj, type):
            setattr(rs, name, obj)
    return rs


def test_realsense_intrinsics_units_and_ir_scaling(monkeypatch):
    rs = fake_realsense(scale=0.00025)  # an L515-like scale: 4 units per mm
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    d = RealSenseDriver(serial="f123", timeout_ms=10)
    d.open()
    assert ("device", "f123") in rs.calls
    assert (rs.stream.depth, 848, 480, rs.format.z16, 30) in rs.calls
    assert (rs.stream.infrared, 1, 848, 480, rs.format.y8, 30) in rs.calls
    cam = Camera.from_json(d.intrinsics())
    assert (cam.width, cam.height, cam.fx, cam.cy) == (848, 480, 421.0, 238.7)
    assert d.intrinsics()["depth_scale_m"] == 0.00025
    it = d.frames()
    ts1, ir, depth = next(it)
    ts3, _, _ = next(it)  # one timeout in between
    assert ts1 == round((1234.5 + 33.3333) * 1e6) and ts3 - ts1 == round(2 * 33.3333e6)
    assert depth.dtype == np.uint16 and depth[5, 5] == 250 and depth[0, 0] == 0
    assert ir.dtype == np.uint16 and ir[5, 5] == 128 * 257 and ir[0, 0] == 65535
    d.close()
    assert rs.calls[-1] == ("stop",)


def test_realsense_rejects_non_brown_conrady_distortion(monkeypatch):
    rs = fake_realsense(model="inverse_brown_conrady", coeffs=[0.1, 0, 0, 0, 0])
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    with pytest.raises(DriverError, match="not Brown-Conrady"):
        RealSenseDriver().open()
    # Zero coefficients mean no distortion whatever the model is called.
    rs = fake_realsense(model="inverse_brown_conrady")
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    d = RealSenseDriver()
    d.open()
    assert d.intrinsics()["depth_intrinsics"]["k1"] == 0.0


def test_ir8_scaling_keeps_saturation():
    a = np.array([[0, 1, 128, 255]], np.uint8)
    assert ir8_to_u16(a).tolist() == [[0, 257, 32896, 65535]]


# --------------------------------------------------------------------------- missing libraries


@pytest.mark.parametrize(
    ("name", "package"),
    [("kinect2", "pylibfreenect2"), ("k4a", "pyk4a"), ("realsense", "pyrealsense2")],
)
def test_missing_library_names_the_pip_package(monkeypatch, name, package):
    monkeypatch.setitem(sys.modules, package, None)  # makes the import fail
    d = make_driver(name)
    with pytest.raises(DriverError, match=rf"needs the Python package '{package}'") as exc:
        d.open()
    assert f"pip install {package}" in str(exc.value)


def test_unknown_driver_and_use_before_open():
    with pytest.raises(DriverError, match="unknown camera driver 'webcam'"):
        make_driver("webcam")
    with pytest.raises(DriverError, match=r"intrinsics\(\) before open\(\)"):
        make_driver("k4a").intrinsics()
