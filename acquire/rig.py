"""Assemble a capture rig: a stage (real port or simulated twin) and a camera.

``open_rig`` is a context manager: it opens the serial port (the only place that does),
starts the simulated stage when asked, and closes everything on exit. `offset_for_stage` gives
the mounting offset a capture with a stage commands: the dataset's calibration, when it was
measured on that stage (`stage_identity`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import stat
from pathlib import Path
from typing import Iterator

import serial

from acquire.camera import CameraKind, Gphoto2Camera
from acquire.ell14 import Ell14
from acquire.sim_ell14 import SimulatedEll14
from acquire.virtual_camera import VirtualCamera, make_glass_scene, make_polarized_target
from urd.core.dataset import Dataset, OffsetCalibration, Scene
from urd.core.errors import CalibrationError, DeviceError

SIM = "sim"

#: Deadline for writing a command to the stage's port (s). A command is at most 11 bytes, 11 ms
#: at 9600 baud; the line has no flow control, so a write that cannot finish means a hung adapter.
WRITE_TIMEOUT_S = 1.0


@dataclasses.dataclass
class SimSettings:
    """Knobs of the simulated stage and virtual camera (simulation only). With
    ``target_angle_deg`` set, the virtual camera sees a polarizer calibration target instead
    of a glass scene."""

    offset_deg: float = 0.0
    jitter_deg: float = 0.0
    faults: dict[str, float] = dataclasses.field(default_factory=dict)
    width: int = 1536
    height: int = 1024
    shake_px: float = 4.0
    shake_deg: float = 0.5
    reflection: Path | None = None
    transmission: Path | None = None
    seed: int = 0
    target_angle_deg: float | None = None
    reversed: bool = False


def stage_identity(stage_info: dict) -> dict:
    """Which stage a ``stage`` record of the rig (`open_rig`'s ``info["stage"]``) describes, for
    telling stages apart: a real ELL14 by serial number and address; the simulated twin by its
    mounting offset, the one setting that moves the polarizer's axis (jitter, faults and seed
    change how it moves, not where its zero is)."""
    simulated = stage_info.get("simulated")
    if simulated is not None:
        mount = {"sim_reversed": True} if simulated.get("reversed") else {}     # another mount of the polarizer
        return {"kind": "ELL14 simulator", "sim_offset_deg": float(simulated["offset_deg"]), **mount}
    return {"kind": "ELL14", "serial": stage_info.get("serial"), "address": stage_info.get("address")}


def _sim_options(identity: dict) -> str:
    """The options that make the calibration command run on the simulated stage ``identity``
    (`stage_identity`): its camera and its mounting offset; nothing for a real stage."""
    if identity.get("kind") != "ELL14 simulator":
        return ""
    return f" --camera virtual --sim-offset {identity['sim_offset_deg']:g}" + (" --sim-reversed" if identity.get("sim_reversed") else "")


def describe_stage(identity: dict) -> str:
    """A `stage_identity` in words, e.g. 'the ELL14 with serial 11400123 at address 0'."""
    if identity.get("kind") == "ELL14 simulator":
        return f"the simulated ELL14 with --sim-offset {identity['sim_offset_deg']:g}" + (" --sim-reversed" if identity.get("sim_reversed") else "")
    return f"the ELL14 with serial {identity.get('serial')} at address {identity.get('address')}"


@dataclasses.dataclass
class Rig:
    stage: Ell14
    camera: object
    info: dict
    sim: SimulatedEll14 | None = None


MISSING_PORT_HINT = ("is the stage connected and powered? Its USB adapter is usually /dev/ttyUSB0 "
                     "(ls /dev/ttyUSB*); --stage sim runs the simulated stage")


def _not_serial(port: str, what: str) -> DeviceError:
    """The error for a ``port`` that names ``what`` (a regular file, a folder, ...) instead of a serial device."""
    return DeviceError(f"{port} is not a serial device ({what}); name the stage's serial port, "
                       "usually /dev/ttyUSB0 (ls /dev/ttyUSB*), or --stage sim for the simulated stage")


def check_port(port: str) -> None:
    """DeviceError, before the port is opened, when ``port`` names nothing or something other than
    a character device (a regular file, a folder, a socket): no serial line is there."""
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        raise DeviceError(f"cannot open serial port {port}: no such device; {MISSING_PORT_HINT}") from None
    except OSError:
        return                                       # opening it says what is wrong (e.g. no permission)
    if not stat.S_ISCHR(mode):
        raise _not_serial(port, "a folder" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode)
                          else "not a character device")


def open_serial(port: str, timeout_s: float = 0.1) -> serial.Serial:
    """Open a serial port at the ELL14's settings (9600 8N1), exclusively: a second capture on
    the same stage would turn it under the first one's shots. DeviceError, with what to check, if
    it cannot (also for a device that takes no serial settings, like /dev/null). A write that does
    not finish within `WRITE_TIMEOUT_S` raises serial's time-out, which the driver reports as a
    lost connection."""
    try:
        return serial.Serial(port, 9600, bytesize=8, parity="N", stopbits=1, timeout=timeout_s,
                             write_timeout=WRITE_TIMEOUT_S, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        cause = exc.__cause__ or exc.__context__
        if cause is not None and cause.args[:1] == (errno.ENOTTY,):
            raise _not_serial(port, "it takes no serial line settings") from exc
        if "exclusively lock" in str(exc):
            hint = "another program (another urd capture?) is using it; wait for it or stop it"
        elif isinstance(exc, FileNotFoundError) or "No such file" in str(exc):
            hint = MISSING_PORT_HINT
        else:
            hint = "check the port name and that you may use it (on Linux, membership of the 'dialout' group)"
        raise DeviceError(f"cannot open serial port {port}: {exc}; {hint}") from exc


@contextlib.contextmanager
def open_rig(stage: str, camera: str, address: str = "0", sim: SimSettings | None = None) -> Iterator[Rig]:
    """Open the stage on ``stage`` (a port, or 'sim') and the ``camera`` kind. A port that is no
    serial device (`check_port`), and the virtual camera without the simulated stage, are refused
    before the port is opened."""
    sim = sim or SimSettings()
    try:
        kind = CameraKind(camera)
    except ValueError:
        raise DeviceError(f"unknown camera {camera!r}; expected one of {[k.value for k in CameraKind]}") from None
    if stage != SIM:
        check_port(stage)
        if kind is CameraKind.VIRTUAL:
            raise DeviceError("the virtual camera needs the simulated stage (--stage sim): it reads the true polarizer angle from it")
    with contextlib.ExitStack() as stack:
        twin = None
        if stage == SIM:
            twin = stack.enter_context(SimulatedEll14(address, sim_offset_deg=sim.offset_deg, sim_jitter_deg=sim.jitter_deg,
                                                      sim_faults=sim.faults, seed=sim.seed, sim_reversed=sim.reversed))
            port_name = twin.port_name
        else:
            port_name = stage
        port = stack.enter_context(open_serial(port_name))
        driver = stack.enter_context(Ell14(port, address))
        info = driver.info()
        stage_info = {"kind": "ELL14", "port": stage, "address": address, "serial": info.serial_number,
                      "firmware": info.firmware, "pulses_per_rev": info.pulses_per_rev}
        if kind is CameraKind.VIRTUAL:
            if sim.target_angle_deg is None:
                scene = make_glass_scene(sim.width, sim.height, sim.reflection, sim.transmission)
            else:
                scene = make_polarized_target(sim.width, sim.height, sim.target_angle_deg)
            cam = VirtualCamera(scene, twin.true_angle_deg, sim.shake_px, sim.shake_deg, seed=sim.seed)
        else:
            try:
                cam = Gphoto2Camera()
            except DeviceError as exc:
                raise DeviceError(f"{exc}; without a camera, --camera virtual (with --stage sim) simulates one") from exc
        camera_info = cam.describe()
        if kind is CameraKind.VIRTUAL:
            camera_info.update(reflection=_image_name(sim.reflection), transmission=_image_name(sim.transmission))
        if twin is not None:
            stage_info["simulated"] = {"offset_deg": sim.offset_deg, "jitter_deg": sim.jitter_deg, "faults": sim.faults,
                                       "seed": sim.seed, **({"reversed": True} if sim.reversed else {})}
        yield Rig(driver, cam, {"stage": stage_info, "camera": camera_info}, twin)


def _image_name(path: Path | None) -> str | None:
    """An image file of the virtual camera's scene as an absolute path (None: the bundled photo)."""
    return None if path is None else str(Path(path).resolve())


def calibration_stage(ds: Dataset) -> dict | None:
    """The identity (`stage_identity`) of the stage the dataset's mounting offset
    was calibrated on: as recorded in ``calibration.json``, else (calibrations written before
    it was recorded) from the sweep's manifest; None when not known."""
    calibration = ds.calibration()
    return None if calibration is None else calibration_owner(calibration)


def calibration_owner(calibration: OffsetCalibration) -> dict | None:
    """The identity of the stage ``calibration`` was measured on: as it records it, else (records
    written before it was recorded) from its sweep's manifest; None when not known."""
    stage = calibration.stage
    if stage is None and calibration.sweep is not None and Scene(calibration.sweep).exists():
        recorded = Scene(calibration.sweep).load(verify=False)["capture"].get("stage")
        stage = None if recorded is None else stage_identity(recorded)
    return stage


def offset_for_stage(ds: Dataset, stage_info: dict) -> tuple[float, str]:
    """The mounting offset (deg) a new capture with the stage ``stage_info`` (`open_rig`'s
    ``info["stage"]``) commands, and a line saying which calibration that is.

    0 without a calibration. CalibrationError when the dataset's calibration belongs to
    another stage (its offset would put every shot at the wrong angle).
    """
    calibration = ds.calibration()
    if calibration is None:
        return 0.0, "mounting offset: not calibrated (urd calibrate offset); stage zero taken as polarizer angle 0 deg"
    owner, this = calibration_stage(ds), stage_identity(stage_info)
    if owner is not None and owner != this:
        raise CalibrationError(
            f"{ds.calibration_path.resolve()}: the mounting offset {calibration.offset_deg:.3f} deg was calibrated on "
            f"{describe_stage(owner)}, not on this stage ({describe_stage(this)}); calibrate this stage "
            f"with 'urd calibrate offset {ds.root.resolve()} --stage {stage_info.get('port') or 'PORT'}"
            f"{_sim_options(this)}', or capture into another dataset")
    whose = describe_stage(owner) if owner is not None else "a stage it does not record"
    sense = ("" if calibration.direction is not None else
             "; the stage's sense of rotation is not checked (urd calibrate offset --check-direction)")
    return calibration.offset_deg, (f"mounting offset: {calibration.offset_deg:.3f} ± {calibration.uncertainty_deg:.3f} deg "
                                    f"from {ds.calibration_path.resolve()} ({calibration.time}, on {whose}){sense}")
