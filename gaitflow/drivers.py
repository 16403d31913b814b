"""Live depth-camera drivers behind one interface (issue 3, item 5).

Every driver follows :class:`CameraDriver`: ``open()``, ``intrinsics()`` (the camera.json
document of ``shared/spec/session-folder.md``, read from the device), ``frames()`` (an
iterator of ``(timestamp_ns, ir, depth)``) and ``close()``.

Array conventions: ``ir`` and ``depth`` are uint16 (row, col) arrays of the depth sensor's
size. IR is amplitude 0..65535 (65535 = saturated); depth is Z in mm (0 = invalid). The
IR and depth images of every driver come from the same sensor (or, for RealSense, the left
IR imager that the depth map is computed in), so no registration is needed.

Drivers:

- ``kinect2``: Kinect v2 through libfreenect2 (``pip install pylibfreenect2``). IR and
  depth arrive as float32 (IR already 0..65535, depth in mm) and are rounded to uint16.
  The timestamp is the device's, in units of 0.1 ms.
- ``k4a``: Azure Kinect, and Orbbec Femto through Orbbec's K4A wrapper, through pyk4a
  (``pip install pyk4a``). IR and depth are uint16 already. The device's 8-coefficient
  rational distortion model is refitted to the 5-coefficient Brown-Conrady model gaitflow
  uses (see :func:`fit_brown_conrady`); the fit's RMS error is stored in camera.json.
- ``realsense``: Intel RealSense D400 through pyrealsense2 (``pip install pyrealsense2``).
  Depth units are converted to mm with the device's depth scale; the left IR image is Y8
  (8-bit) and is scaled by 257 so 0 -> 0 and 255 -> 65535 (8-bit saturation stays
  saturation).

Each library is imported lazily, inside ``open()``; when it is absent the driver raises
:class:`DriverError` naming the pip package. Tests inject fake modules with the same API.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Iterator
from types import ModuleType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from gaitflow.camera import Camera
from gaitflow.errors import DriverError

log = logging.getLogger("gaitflow.drivers")

DriverFrame = tuple[int, np.ndarray, np.ndarray]


@runtime_checkable
class CameraDriver(Protocol):
    """The interface every live camera driver implements."""

    name: str

    def open(self) -> None:
        """Connect to the device and start the IR and depth streams."""

    def intrinsics(self) -> dict[str, Any]:
        """The depth sensor's camera.json document, read from the device."""

    def frames(self) -> Iterator[DriverFrame]:
        """Frames as ``(timestamp_ns, ir uint16 (H, W), depth uint16 (H, W) mm)``."""

    def close(self) -> None:
        """Stop the streams and release the device. Safe to call twice."""


def import_driver_module(module: str, package: str, driver: str, extra: str) -> ModuleType:
    """Import a driver library, or raise DriverError saying which package to install."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DriverError(
            f"camera driver {driver!r} needs the Python package {package!r}, which is not "
            f"installed: pip install {package}  (or: pip install 'gaitflow[{extra}]'); "
            f"import error: {exc}"
        ) from exc


# --------------------------------------------------------------------------- pure converters


def float_to_u16(a: np.ndarray) -> np.ndarray:
    """float32 (H, W) image -> uint16 (H, W), rounded; NaN, inf and < 0 give 0.

    Values above 65535 saturate at 65535 (for IR that is the saturated value).
    """
    a = np.asarray(a, dtype=np.float32)
    out = np.where(np.isfinite(a) & (a > 0), a, 0.0)
    return np.minimum(np.rint(out), 65535).astype(np.uint16)


def depth_float_mm_to_u16(a: np.ndarray) -> np.ndarray:
    """float depth in mm (H, W) -> uint16 mm; invalid (NaN, <= 0, > 65535) -> 0.

    Depth beyond the uint16 range is not clipped to 65535: a wrong depth is worse than none.
    """
    a = np.asarray(a, dtype=np.float64)
    r = np.rint(np.where(np.isfinite(a), a, 0.0))
    return np.where((r > 0) & (r <= 65535), r, 0).astype(np.uint16)


def ir8_to_u16(a: np.ndarray) -> np.ndarray:
    """8-bit IR (H, W) -> 16-bit by x257: 0 -> 0, 255 -> 65535 (saturated stays saturated)."""
    return np.asarray(a, dtype=np.uint8).astype(np.uint16) * np.uint16(257)


def depth_units_to_mm(raw: np.ndarray, scale_m: float) -> np.ndarray:
    """Device depth units (uint16 (H, W)) times ``scale_m`` metres/unit -> uint16 mm."""
    raw = np.asarray(raw)
    if abs(scale_m - 0.001) < 1e-9:
        return raw.astype(np.uint16, copy=True)
    return depth_float_mm_to_u16(raw.astype(np.float64) * (scale_m * 1000.0))


def fit_brown_conrady(
    coeffs: np.ndarray | list[float],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    grid: int = 41,
) -> tuple[dict[str, float], float]:
    """Refit OpenCV rational distortion to 5-coefficient Brown-Conrady.

    ``coeffs`` is OpenCV's order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``. The rational model
    divides the radial term by ``1 + k4 r^2 + k5 r^4 + k6 r^6``; gaitflow's camera model
    (and the session-folder spec) has no denominator, so the distortion is sampled on a
    ``grid`` x ``grid`` lattice over the image and k1, k2, k3, p1, p2 are solved by linear
    least squares (the distortion is linear in them).

    Returns the coefficients and the RMS reprojection difference in pixels.
    """
    c = [float(x) for x in coeffs] + [0.0] * 8
    k1, k2, p1, p2, k3, k4, k5, k6 = c[:8]
    if k4 == 0.0 and k5 == 0.0 and k6 == 0.0:
        return {"k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2}, 0.0
    # Sample undistorted normalised points whose distorted images cover the frame: start
    # from the pixel lattice and treat it as undistorted, which covers the same field.
    us = np.linspace(0, width - 1, grid)
    vs = np.linspace(0, height - 1, grid)
    uu, vv = np.meshgrid(us, vs)
    x = ((uu - cx) / fx).ravel()
    y = ((vv - cy) / fy).ravel()
    r2 = x * x + y * y
    rad = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    # Residual (xd - x, yd - y) = A @ (k1, k2, k3, p1, p2), scaled to pixels per axis.
    ax = np.stack([x * r2, x * r2**2, x * r2**3, 2 * x * y, r2 + 2 * x * x], axis=1) * fx
    ay = np.stack([y * r2, y * r2**2, y * r2**3, r2 + 2 * y * y, 2 * x * y], axis=1) * fy
    A = np.concatenate([ax, ay])
    b = np.concatenate([(xd - x) * fx, (yd - y) * fy])
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    resid = A @ sol - b
    rms = float(np.sqrt(np.mean(resid[: len(x)] ** 2 + resid[len(x) :] ** 2)))
    names = ("k1", "k2", "k3", "p1", "p2")
    return {n: float(v) for n, v in zip(names, sol, strict=True)}, rms


# --------------------------------------------------------------------------- base


class _Driver:
    """Shared bookkeeping: state checks, counters and the consecutive-timeout limit."""

    name = "driver"
    package = ""
    module = ""
    extra = ""

    def __init__(
        self, lib: ModuleType | None = None, timeout_ms: int = 1000, max_timeouts: int = 5
    ) -> None:
        self._lib = lib
        self.timeout_ms = int(timeout_ms)
        self.max_timeouts = int(max_timeouts)
        self._doc: dict[str, Any] | None = None
        self._open = False
        self.frames_delivered = 0
        self.frames_bad = 0
        self.timeouts = 0
        self._consecutive = 0

    def _import(self) -> ModuleType:
        if self._lib is None:
            self._lib = import_driver_module(self.module, self.package, self.name, self.extra)
        return self._lib

    def intrinsics(self) -> dict[str, Any]:
        if self._doc is None:
            raise DriverError(f"camera driver {self.name!r}: intrinsics() before open()")
        return dict(self._doc)

    @property
    def shape(self) -> tuple[int, int]:
        doc = self.intrinsics()
        return (int(doc["height"]), int(doc["width"]))

    def _timeout(self) -> None:
        self.timeouts += 1
        self._consecutive += 1
        if self._consecutive >= self.max_timeouts:
            raise DriverError(
                f"camera driver {self.name!r}: no frame for {self._consecutive} x "
                f"{self.timeout_ms} ms; is the camera connected and streaming?"
            )

    def _deliver(self, ts_ns: int, ir: np.ndarray, depth: np.ndarray) -> DriverFrame | None:
        """Check one converted frame; count and drop it if its shape is wrong."""
        self._consecutive = 0
        if ir.shape != self.shape or depth.shape != self.shape:
            self.frames_bad += 1
            log.warning(
                "%s: dropped frame with IR %s / depth %s, expected %s",
                self.name,
                ir.shape,
                depth.shape,
                self.shape,
            )
            return None
        self.frames_delivered += 1
        return int(ts_ns), ir, depth

    def _doc_from(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        dist: dict[str, float],
        width: int,
        height: int,
        fps: float,
        model: str,
        **extra: Any,
    ) -> dict[str, Any]:
        cam = Camera(
            width=int(width),
            height=int(height),
            fps=float(fps),
            fx=float(fx),
            fy=float(fy),
            cx=float(cx),
            cy=float(cy),
            model=model,
            **{k: float(v) for k, v in dist.items()},
        )
        return cam.to_json(driver=self.name, **extra)

    def __enter__(self) -> _Driver:
        self.open()  # type: ignore[attr-defined]
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()  # type: ignore[attr-defined]


# --------------------------------------------------------------------------- Kinect v2


class Kinect2Driver(_Driver):
    """Kinect v2 through libfreenect2's Python bindings (pylibfreenect2).

    Parameters
    ----------
    serial : device serial number (default: the first device).
    pipeline : libfreenect2 depth packet pipeline: "auto" (OpenGL, then OpenCL, then CPU),
        "opengl", "opencl", "cuda" or "cpu".
    """

    name = "kinect2"
    package = "pylibfreenect2"
    module = "pylibfreenect2"
    extra = "kinect"
    # libfreenect2::Frame::timestamp is in units of 0.1 ms ("roughly or exactly").
    TICK_NS = 100_000

    def __init__(self, serial: str | None = None, pipeline: str = "auto", **kw: Any) -> None:
        super().__init__(**kw)
        self.serial, self.pipeline_name = serial, pipeline
        self._fn = self._device = self._listener = None
        self._last_tick: int | None = None
        self._wraps = 0

    def _pipeline(self, lib: ModuleType) -> Any:
        names = {
            "opengl": "OpenGLPacketPipeline",
            "opencl": "OpenCLPacketPipeline",
            "cuda": "CudaPacketPipeline",
            "cpu": "CpuPacketPipeline",
        }
        order = (
            ["opengl", "opencl", "cpu"] if self.pipeline_name == "auto" else [self.pipeline_name]
        )
        for key in order:
            cls = getattr(lib, names.get(key, ""), None)
            if cls is not None:
                return cls()
        raise DriverError(
            f"camera driver 'kinect2': libfreenect2 has no {self.pipeline_name!r} pipeline"
        )

    def open(self) -> None:
        lib = self._import()
        fn = lib.Freenect2()
        if fn.enumerateDevices() == 0:
            raise DriverError("camera driver 'kinect2': no Kinect v2 found (check USB 3 power)")
        serial = self.serial or fn.getDeviceSerialNumber(0)
        device = fn.openDevice(serial, pipeline=self._pipeline(lib))
        if device is None:
            raise DriverError(f"camera driver 'kinect2': cannot open device {serial!r}")
        listener = lib.SyncMultiFrameListener(lib.FrameType.Ir | lib.FrameType.Depth)
        device.setIrAndDepthFrameListener(listener)
        device.startStreams(rgb=False, depth=True)
        self._fn, self._device, self._listener = fn, device, listener
        self._open = True
        # The factory parameters are read from the device when streaming starts.
        p = device.getIrCameraParams()
        dist = {"k1": p.k1, "k2": p.k2, "k3": p.k3, "p1": p.p1, "p2": p.p2}
        self._doc = self._doc_from(
            p.fx,
            p.fy,
            p.cx,
            p.cy,
            dist,
            512,
            424,
            30.0,
            "kinect-v2",
            serial=str(serial),
        )

    def _ns(self, tick: int) -> int:
        # The device counter is uint32: unwrap so capture times keep increasing.
        if self._last_tick is not None and tick < self._last_tick:
            self._wraps += 1
        self._last_tick = tick
        return (tick + self._wraps * (1 << 32)) * self.TICK_NS

    def frames(self) -> Iterator[DriverFrame]:
        if not self._open:
            raise DriverError("camera driver 'kinect2': frames() before open()")
        while self._open:
            fm = self._listener.waitForNewFrame(milliseconds=self.timeout_ms)
            if fm is None:
                self._timeout()
                continue
            try:
                ir, depth = fm["ir"], fm["depth"]
                ts = self._ns(int(ir.timestamp))
                # asarray() views libfreenect2's buffer: convert (copy) before release.
                ir16 = float_to_u16(ir.asarray(np.float32))
                d16 = depth_float_mm_to_u16(depth.asarray(np.float32))
            finally:
                self._listener.release(fm)
            out = self._deliver(ts, ir16, d16)
            if out is not None:
                yield out

    def close(self) -> None:
        if self._device is not None:
            dev, self._device = self._device, None
            self._open = False
            dev.stop()
            dev.close()


# --------------------------------------------------------------------------- Azure Kinect


# Depth-mode resolutions (width, height) of the Azure Kinect (and Orbbec Femto wrapper).
K4A_MODES = {
    "NFOV_2X2BINNED": (320, 288),
    "NFOV_UNBINNED": (640, 576),
    "WFOV_2X2BINNED": (512, 512),
    "WFOV_UNBINNED": (1024, 1024),
}


class K4ADriver(_Driver):
    """Azure Kinect / Orbbec Femto through pyk4a.

    Parameters
    ----------
    device_id : index of the device.
    depth_mode : one of :data:`K4A_MODES`; NFOV_UNBINNED (75 x 65 deg, 640 x 576) is the
        closest to a Kinect v2's field of view.
    fps : 5, 15 or 30 (WFOV_UNBINNED allows at most 15).
    """

    name = "k4a"
    package = "pyk4a"
    module = "pyk4a"
    extra = "azure"

    def __init__(
        self, device_id: int = 0, depth_mode: str = "NFOV_UNBINNED", fps: int = 30, **kw: Any
    ) -> None:
        super().__init__(**kw)
        if depth_mode not in K4A_MODES:
            raise DriverError(
                f"camera driver 'k4a': depth_mode {depth_mode!r} is not one of {list(K4A_MODES)}"
            )
        if fps not in (5, 15, 30):
            raise DriverError(f"camera driver 'k4a': fps {fps!r} is not 5, 15 or 30")
        self.device_id, self.depth_mode, self.fps = device_id, depth_mode, fps
        self._dev = None

    def open(self) -> None:
        lib = self._import()
        cfg = lib.Config(
            color_resolution=lib.ColorResolution.OFF,
            depth_mode=getattr(lib.DepthMode, self.depth_mode),
            camera_fps=getattr(lib.FPS, f"FPS_{self.fps}"),
            # Without a colour stream there is nothing to synchronise with.
            synchronized_images_only=False,
        )
        dev = lib.PyK4A(cfg, device_id=self.device_id)
        try:
            dev.start()
        except getattr(lib, "K4AException", RuntimeError) as exc:
            raise DriverError(f"camera driver 'k4a': cannot start device: {exc}") from exc
        self._dev, self._open = dev, True
        cal = dev.calibration
        K = np.asarray(cal.get_camera_matrix(lib.CalibrationType.DEPTH), dtype=np.float64)
        coeffs = np.asarray(
            cal.get_distortion_coefficients(lib.CalibrationType.DEPTH), dtype=np.float64
        )
        w, h = K4A_MODES[self.depth_mode]
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        dist, rms = fit_brown_conrady(coeffs, fx, fy, cx, cy, w, h)
        self._doc = self._doc_from(
            fx,
            fy,
            cx,
            cy,
            dist,
            w,
            h,
            float(self.fps),
            "azure-kinect",
            depth_mode=self.depth_mode,
            rational_distortion=[float(c) for c in coeffs],
            distortion_fit_rms_px=rms,
        )

    def frames(self) -> Iterator[DriverFrame]:
        if not self._open:
            raise DriverError("camera driver 'k4a': frames() before open()")
        lib = self._import()
        timeout_exc = getattr(lib, "K4ATimeoutException", TimeoutError)
        while self._open:
            try:
                cap = self._dev.get_capture(timeout=self.timeout_ms)
            except timeout_exc:
                self._timeout()
                continue
            ir, depth = cap.ir, cap.depth
            if ir is None or depth is None:
                # A capture may lack an image (pyk4a gives no guarantee): count it.
                self.frames_bad += 1
                continue
            ts = int(cap.depth_timestamp_usec) * 1000
            out = self._deliver(
                ts, np.asarray(ir, dtype=np.uint16).copy(), np.asarray(depth, np.uint16).copy()
            )
            if out is not None:
                yield out

    def close(self) -> None:
        if self._dev is not None:
            dev, self._dev = self._dev, None
            self._open = False
            dev.stop()


# --------------------------------------------------------------------------- RealSense


class RealSenseDriver(_Driver):
    """Intel RealSense D400 through pyrealsense2: depth plus the left IR imager (Y8).

    The depth map of a D400 is computed in the left IR imager's frame, so IR pixel (u, v)
    and depth pixel (u, v) coincide, as the session format requires.

    Parameters
    ----------
    width, height, fps : a depth/IR mode the camera supports (848 x 480 at 30 is the
        recommended D435 depth mode).
    serial : device serial (default: any).
    """

    name = "realsense"
    package = "pyrealsense2"
    module = "pyrealsense2"
    extra = "realsense"

    def __init__(
        self,
        width: int = 848,
        height: int = 480,
        fps: int = 30,
        serial: str | None = None,
        **kw: Any,
    ) -> None:
        super().__init__(**kw)
        self.width, self.height, self.fps, self.serial = width, height, fps, serial
        self._pipe = None
        self.depth_scale_m = 0.001

    def open(self) -> None:
        rs = self._import()
        pipe = rs.pipeline()
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        cfg.enable_stream(rs.stream.infrared, 1, self.width, self.height, rs.format.y8, self.fps)
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise DriverError(f"camera driver 'realsense': cannot start: {exc}") from exc
        self._pipe, self._open = pipe, True
        self.depth_scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
        intr = profile.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        coeffs = [float(c) for c in intr.coeffs]
        model = intr.model
        plain = (rs.distortion.brown_conrady, rs.distortion.none)
        if any(coeffs) and model not in plain:
            raise DriverError(
                f"camera driver 'realsense': depth distortion model {model} with "
                f"coefficients {coeffs} is not Brown-Conrady"
            )
        k1, k2, p1, p2, k3 = (coeffs + [0.0] * 5)[:5]
        self._doc = self._doc_from(
            intr.fx,
            intr.fy,
            intr.ppx,
            intr.ppy,
            {"k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2},
            intr.width,
            intr.height,
            float(self.fps),
            "realsense",
            depth_scale_m=self.depth_scale_m,
        )

    def frames(self) -> Iterator[DriverFrame]:
        if not self._open:
            raise DriverError("camera driver 'realsense': frames() before open()")
        while self._open:
            try:
                fs = self._pipe.wait_for_frames(self.timeout_ms)
            except RuntimeError:
                # librealsense signals a timeout with RuntimeError("Frame didn't arrive...").
                self._timeout()
                continue
            d, ir = fs.get_depth_frame(), fs.get_infrared_frame(1)
            if not d or not ir:
                self.frames_bad += 1
                continue
            # Frameset timestamps are milliseconds (double).
            ts = round(float(fs.get_timestamp()) * 1e6)
            depth = depth_units_to_mm(np.asanyarray(d.get_data()), self.depth_scale_m)
            ir16 = ir8_to_u16(np.asanyarray(ir.get_data()))
            out = self._deliver(ts, ir16, depth)
            if out is not None:
                yield out

    def close(self) -> None:
        if self._pipe is not None:
            pipe, self._pipe = self._pipe, None
            self._open = False
            pipe.stop()


DRIVERS: dict[str, type[_Driver]] = {
    "kinect2": Kinect2Driver,
    "k4a": K4ADriver,
    "realsense": RealSenseDriver,
}


def make_driver(name: str, **kw: Any) -> CameraDriver:
    """A driver by name (kinect2, k4a, realsense); the library is imported at ``open()``."""
    try:
        cls = DRIVERS[name]
    except KeyError as exc:
        raise DriverError(f"unknown camera driver {name!r}; known: {sorted(DRIVERS)}") from exc
    return cls(**kw)  # type: ignore[return-value]
