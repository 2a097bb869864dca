"""The one error tree of urd. Every error urd raises on purpose derives from `UrdError`."""


class UrdError(Exception):
    """Root of all urd errors."""


class DeviceError(UrdError):
    """A device (stage, camera) failed or reported a fault."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device did not answer within its timeout."""


class ProtocolError(DeviceError):
    """A device answered, but not in its protocol (garbled, wrong address, not the expected device)."""


class RawFormatError(UrdError, ValueError):
    """A file is not a RAW image urd can decode, or is corrupt."""


class ManifestError(UrdError, ValueError):
    """A manifest is missing, invalid, or does not match the files it describes."""


class DatasetError(UrdError, OSError):
    """A dataset or scene folder is missing, already exists, or cannot be written."""


class AlignmentError(UrdError):
    """The shots of a scene could not be aligned reliably."""


class CalibrationError(UrdError):
    """A calibration fit failed or its input is insufficient."""


class WeightsError(UrdError):
    """A weights file is missing, corrupt, or does not fit the model."""


class DiskFullError(DatasetError):
    """No room left on the disk for a file urd writes (the message names the file)."""


class DatasetBusyError(DatasetError):
    """Another process holds the dataset's write lock."""


class CaptureInterrupted(UrdError):
    """A capture was stopped by the user (Ctrl-C, or SIGTERM where ``terminated``); its completed
    shots are kept."""

    def __init__(self, message: str, terminated: bool = False):
        super().__init__(message)
        self.terminated = terminated


class TrainingError(UrdError):
    """A training run cannot go on: its folder is busy, or it was started with another config."""
