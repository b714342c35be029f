"""The stores: one module per on-disk artifact, the only code that knows its names.

Each module owns one artifact of a processed folder (``docs/reference/outputs.md``): its file and
array names, attributes, format versions and the branches for older files, and hands
out typed readers and writers. Stages read and write through these modules only.

========================  ==================================================
module                    artifact
========================  ==================================================
:mod:`.paths`             where each artifact lives in a processed folder
:mod:`.capture`           ``capture.yaml`` and its photos (the input)
:mod:`.images`            8-bit photos (PNG, JPEG, TIFF) and their EXIF
:mod:`.exr`               OpenEXR files (the low-level reader and writer)
:mod:`.hdr`               merged HDR frames and the camera response
:mod:`.camera`            intrinsics and per-view poses
:mod:`.lights`            the lights found from the highlights' lobes
:mod:`.radiometry`        the flat-field and colour correction of the frames
:mod:`.observation`       the observation map (``observation.zarr``)
:mod:`.fit`               fit stores (``fit/<model>.zarr``)
:mod:`.params`            parameter maps (``params/<model>.exr``)
:mod:`.metrics`           ``metrics/<stage>.json``
:mod:`.common`            what every zarr store shares (completion mark, sizes)
========================  ==================================================
"""
