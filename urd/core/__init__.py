"""urd's base layer: what every other package may import and what imports none of them.

`errors` (the error tree), `files` (atomic files, hashes and locks), `manifest` (the manifest
schema and its checks), `dataset` (scenes and datasets), `images` (image files and the linear
codes urd stores), `raw` (RAW decoding through rawpy), `mosaic` (polarization-camera layouts and
demosaicing), `align` (ECC alignment of sequential shots), `progress` (progress reporting) and
`samples` (the real captures in ../shared/data). The hardware (`acquire`), calibration
(`calib`) and separation (`separate`) packages build on it; the workflows and the CLI
(`urd.ingest`, `urd.separation`, `urd.batch`, `urd.report`, `urd.demo`, `urd.api`, `urd.cli`)
sit on top.
"""

__version__ = "0.1.0"
