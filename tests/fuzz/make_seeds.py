#!/usr/bin/python3
"""Writes the hand-made seeds of tests/fuzz/corpus/ (the others are copies of the demo's files).

Small valid files of each format (named valid-*: the readers must accept them), a few near-valid
ones, and files named refused-* that the readers must refuse. Run from anywhere:
python3 tests/fuzz/make_seeds.py [GROUP ...] (default: every group; the groups float_nifti and
dicom_series need neither numpy nor nibabel).

The igtl_stream seeds were packed by the OpenIGTLink library itself (TransformMessage,
TrackingDataMessage, StringMessage; a version-2 header built by hand around a TRANSFORM body;
one with a flipped body bit, the CRC no longer matching).

The plus_sequence seeds valid-video.igs.mha and valid-nrrd.igs.nrrd are copies of the PLUS
toolkit's test files in tests/data/plus-sequence-files (BSD-3-Clause, its licence there);
valid-tracker.igs.mha holds the first six frames of TransformInterpolationTest.igs.mha,
uncompressed, one status made INVALID; the refused-* ones break it (a status neither OK nor
INVALID, data cut short, a frame beyond the time axis).
"""
import gzip
import json
import os
import struct
import sys

try:
    import nibabel as nib
    import numpy as np
except ImportError:  # float_nifti and dicom_series are written without them
    nib = np = None

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "corpus")


def put(target, name, data):
    os.makedirs(os.path.join(HERE, target), exist_ok=True)
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(os.path.join(HERE, target, name), mode) as f:
        f.write(data)


def nifti_bytes(array, affine, dtype):
    image = nib.Nifti1Image(array.astype(dtype), affine)
    image.header.set_xyzt_units("mm")
    return image.to_bytes()


def images():
    grid = np.arange(4 * 3 * 2).reshape(4, 3, 2)
    affine = np.diag([0.7, 0.8, 2.5, 1.0])
    affine[:3, 3] = [-10, 20, 5]
    put("nifti", "valid-float32.nii", nifti_bytes(grid, affine, np.float32))
    oblique = affine.copy()
    oblique[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]) @ affine[:3, :3]
    put("nifti", "valid-int16-rotated.nii", nifti_bytes(grid, oblique, np.int16))
    put("nifti", "truncated.nii", nifti_bytes(grid, affine, np.float32)[:360])

    raw = grid.astype("<f4").tobytes(order="F")
    header = ("NRRD0004\ntype: float\ndimension: 3\nspace: left-posterior-superior\n"
              "sizes: 4 3 2\nspace directions: (0.7,0,0) (0,0.8,0) (0,0,2.5)\n"
              "space origin: (-10,20,5)\nendian: little\nencoding: raw\n\n")
    put("nrrd", "valid-float-raw.nrrd", header.encode() + raw)
    text = " ".join(str(v) for v in grid.flatten(order="F"))
    put("nrrd", "valid-ascii.nrrd", header.replace("raw", "ascii").replace("float", "short") + text + "\n")

    labels = np.zeros((4, 3, 2), dtype="<i2")
    labels[1:3, 1, :] = 5
    mha = ("ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
           "Offset = -10 20 5\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
           "ElementSpacing = 0.7 0.8 2.5\nDimSize = 4 3 2\nElementType = MET_SHORT\n"
           "ElementDataFile = LOCAL\n")
    put("metaimage", "valid-short.mha", mha.encode() + labels.tobytes(order="F"))
    put("metaimage", "valid-uchar.mha",
        mha.replace("MET_SHORT", "MET_UCHAR").encode() + labels.astype("u1").tobytes(order="F"))


def segmentation():
    labels = np.zeros((4, 3, 2), dtype="u1")
    labels[0:2, :, 0] = 1
    labels[2:4, :, 1] = 2
    header = ("NRRD0004\ntype: unsigned char\ndimension: 3\nspace: left-posterior-superior\n"
              "sizes: 4 3 2\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (0,0,0)\n"
              "endian: little\nencoding: raw\n"
              "Segment0_ID:=Segment_1\nSegment0_Name:=liver\nSegment0_LabelValue:=1\n"
              "Segment0_Layer:=0\nSegment0_Color:=0.9 0.6 0.5\n"
              "Segment1_ID:=Segment_2\nSegment1_Name:=Tumor\nSegment1_LabelValue:=2\n"
              "Segment1_Layer:=0\nSegment1_Color:=0.2 0.8 0.2\n\n")
    put("segmentation", "valid-two-segments.seg.nrrd", header.encode() + labels.tobytes(order="F"))
    put("segmentation", "no-segments.seg.nrrd",
        header.split("Segment0_ID")[0].encode() + b"\n" + labels.tobytes(order="F"))


def markups():
    line = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                       "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
            "markups": [{"type": "Line", "coordinateSystem": "RAS", "coordinateUnits": "mm",
                         "controlPoints": [
                             {"id": "1", "label": "entry", "position": [30.0, 40.0, 12.0],
                              "positionStatus": "defined"},
                             {"id": "2", "label": "target", "position": [-5.5, -7.0, -3.0],
                              "positionStatus": "defined"}]}]}
    put("line_markup", "valid-ras.mrk.json", json.dumps(line, indent=1))
    line["markups"][0]["coordinateSystem"] = "LPS"
    put("line_markup", "valid-lps.mrk.json", json.dumps(line))
    fiducials = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
        {"label": "F-1", "position": [10.5, -20.25, 30.0]},
        {"label": "F-2", "position": [-1.0, 2.0, -3.0]},
        {"label": "F-3", "position": [4.0, 8.0, 1.0]}]}]}
    put("fiducial_markups", "valid-lps.mrk.json", json.dumps(fiducials, indent=1))
    fiducials["markups"][0]["coordinateSystem"] = "RAS"
    put("fiducial_markups", "valid-ras.mrk.json", json.dumps(fiducials))


def csvs():
    put("batch_csv", "valid-two.csv",
        "name,entry_x,entry_y,entry_z,target_x,target_y,target_z\n"
        "anterior,10,-80,5,0,0,0\nlateral,-90,0,12.5,1,2,3\n")
    put("batch_csv", "bad-number.csv",
        "name,entry_x,entry_y,entry_z,target_x,target_y,target_z\nx,1e400,0,0,0,0,0\n")
    header = "frame,timestamp_ns,board,state,tx,ty,tz,qw,qx,qy,qz,rms_px\n"
    put("poses_csv", "valid-tracked-and-lost.csv", header +
        "0,0,patient,tracked,142.848559,0.430991,508.263001,0.711398379551,0.025339570469,"
        "-0.006078717257,0.702305703335,0.31\n"
        "0,0,needle,lost,,,,,,,,\n")
    put("poses_csv", "wrong-header.csv", "frame,board\n0,patient\n")


def be(fmt, values):
    return b"".join(struct.pack(">" + fmt, v) for v in values)


def area_mesh():
    vertices = [(0, 0, 0), (10, 0, 0), (0, 10, 0), (0, 0, 10)]
    triangles = [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]
    safe, region, leeway = [1, 1, 0, 1], [0, 0, -1, 0], [2.5, 2.5, 0.0, 1.0]
    s = b"# vtk DataFile Version 3.0\nCrepuscular area safety geometry SPACE=LPS (mm)\n"
    s += b"BINARY\nDATASET POLYDATA\nFIELD FieldData 2\nellipsoid 15 1 double\n"
    s += be("d", [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 20, 15, 10])
    s += b"\narea_settings 5 1 double\n" + be("d", [100, 1, 2, 0.5, 3]) + b"\n"
    s += b"POINTS 4 double\n" + be("d", [c for v in vertices for c in v])
    s += b"\nPOLYGONS 4 16\n" + be("i", [x for t in triangles for x in (3,) + t])
    s += b"\nPOINT_DATA 4\nSCALARS safe unsigned_char 1\nLOOKUP_TABLE default\n" + bytes(safe)
    s += b"\nSCALARS region int 1\nLOOKUP_TABLE default\n" + be("i", region)
    s += b"\nSCALARS leeway float 1\nLOOKUP_TABLE default\n" + be("f", leeway) + b"\n"
    put("area_mesh", "valid-binary.vtk", s)
    a = "# vtk DataFile Version 3.0\nCrepuscular area safety geometry SPACE=LPS (mm)\n"
    a += "ASCII\nDATASET POLYDATA\nFIELD FieldData 2\nellipsoid 15 1 double\n"
    a += "0 0 0 1 0 0 0 1 0 0 0 1 20 15 10\narea_settings 5 1 double\n100 1 2 0.5 3\n"
    a += "POINTS 4 double\n" + " ".join(str(c) for v in vertices for c in v)
    a += "\nPOLYGONS 4 16\n" + "\n".join("3 %d %d %d" % t for t in triangles)
    a += "\nPOINT_DATA 4\nSCALARS safe unsigned_char 1\nLOOKUP_TABLE default\n"
    a += " ".join(map(str, safe)) + "\nSCALARS region int 1\nLOOKUP_TABLE default\n"
    a += " ".join(map(str, region)) + "\nSCALARS leeway float 1\nLOOKUP_TABLE default\n"
    a += " ".join(map(str, leeway)) + "\n"
    put("area_mesh", "valid-ascii.vtk", a)


def small_variants():
    """Second seeds for formats whose first seed is a copy of the demo's file."""
    put("boards", "valid-grid.json", json.dumps({"boards": [{
        "name": "needle", "family": "tag36h11",
        "grid": {"rows": 2, "cols": 2, "first_id": 10, "tag_size_mm": 20, "gap_mm": 5}}]}))
    # valid-demo.json: the demo's scene.json, camera and boards inline, every 40th pose.
    put("scene", "stopped.json", json.dumps({"camera": "camera.yaml", "boards": "boards.json",
                                              "frames": 2, "fps": 30}))


def nifti1(dims, values, fmt, datatype, big_endian=False):
    """A single-file NIfTI-1 of 1 mm voxels written field by field (no orientation codes)."""
    e = ">" if big_endian else "<"
    h = bytearray(352)
    struct.pack_into(e + "i", h, 0, 348)
    struct.pack_into(e + "8h", h, 40, *([len(dims)] + list(dims) + [1] * (7 - len(dims))))
    struct.pack_into(e + "hh", h, 70, datatype, struct.calcsize(fmt) * 8)
    struct.pack_into(e + "8f", h, 76, *([1.0] * 8))
    struct.pack_into(e + "ff", h, 108, 352.0, 1.0)  # vox_offset, scl_slope
    h[344:348] = b"n+1\0"
    return bytes(h) + b"".join(struct.pack(e + fmt, v) for v in values)


def float_nifti():
    """Float voxels: niftilib reads NaN and Inf as 0, so the reader checks them itself."""
    values = [float(i) for i in range(4 * 3 * 2)]
    put("nifti", "valid-float64-big-endian.nii", nifti1((4, 3, 2), values, "d", 64, True))
    nan = values[:]
    nan[13] = float("nan")
    put("nifti", "refused-nan-voxel.nii", nifti1((4, 3, 2), nan, "f", 16))
    inf = values[:]
    inf[23] = float("-inf")
    put("nifti", "refused-inf-voxel-big-endian.nii", nifti1((4, 3, 2), inf, "f", 16, True))
    put("nifti_gz", "valid-float32.nii.gz", gzip.compress(nifti1((4, 3, 2), values, "f", 16), 9, mtime=0))
    put("nifti_gz", "valid-4d-float32.nii.gz",
        gzip.compress(nifti1((2, 2, 1, 2), values[:8], "f", 16), 9, mtime=0))
    put("nifti_gz", "refused-nan-voxel.nii.gz", gzip.compress(nifti1((4, 3, 2), nan, "f", 16), 9, mtime=0))
    put("nifti_gz", "valid-int16.nii.gz",
        gzip.compress(nifti1((4, 3, 2), [int(v) for v in values], "h", 4), 9, mtime=0))


def dicom_element(group, element, vr, value):
    if isinstance(value, str):
        value = value.encode()
        if len(value) % 2:
            value += b"\0" if vr == "UI" else b" "
    if vr in ("OB", "OW"):
        return struct.pack("<HH", group, element) + vr.encode() + b"\0\0" + struct.pack("<I", len(value)) + value
    return struct.pack("<HH", group, element) + vr.encode() + struct.pack("<H", len(value)) + value


def dicom_slice(series_uid, k, z, rows=3, columns=4, description="Abdomen", cut=0):
    """One CT slice (explicit VR little endian, int16) at height z mm, as the tests write them."""
    sop_class, sop = "1.2.840.10008.5.1.4.1.1.2", "%s.%d" % (series_uid, k + 1)
    us = lambda g, e, v: dicom_element(g, e, "US", struct.pack("<H", v))
    meta = (dicom_element(2, 1, "OB", b"\0\1") + dicom_element(2, 2, "UI", sop_class) +
            dicom_element(2, 3, "UI", sop) + dicom_element(2, 0x10, "UI", "1.2.840.10008.1.2.1"))
    data = (dicom_element(8, 0x16, "UI", sop_class) + dicom_element(8, 0x18, "UI", sop) +
            dicom_element(8, 0x60, "CS", "CT") + dicom_element(8, 0x103E, "LO", description) +
            dicom_element(0x20, 0xE, "UI", series_uid) +
            dicom_element(0x20, 0x32, "DS", "-10\\20\\%g" % z) +
            dicom_element(0x20, 0x37, "DS", "1\\0\\0\\0\\1\\0") +
            us(0x28, 2, 1) + dicom_element(0x28, 4, "CS", "MONOCHROME2") + us(0x28, 0x10, rows) +
            us(0x28, 0x11, columns) + dicom_element(0x28, 0x30, "DS", "0.8\\0.7") +
            us(0x28, 0x100, 16) + us(0x28, 0x101, 16) + us(0x28, 0x102, 15) + us(0x28, 0x103, 1) +
            dicom_element(0x7FE0, 0x10, "OW", b"".join(struct.pack("<h", 100 * k + i)
                                                       for i in range(rows * columns))))
    out = (b"\0" * 128 + b"DICM" + b"\x02\x00\x00\x00UL\x04\x00" + struct.pack("<I", len(meta)) +
           meta + data)
    return out[:len(out) - cut]


SLICE_MARK = b"#SLICE#\n"  # tests/fuzz/targets.cpp splits the input into slice files here


def dicom_series():
    """Folders of slices, the slices joined by SLICE_MARK (the dicom_series target's input)."""
    uid = "2.25.99001"  # the series the target chooses where a folder holds several
    put("dicom_series", "valid-three-slices.bin",
        SLICE_MARK.join(dicom_slice(uid, k, 2.5 * k) for k in range(3)))
    put("dicom_series", "valid-chosen-of-two-series.bin",
        SLICE_MARK.join([dicom_slice(uid, k, 2.5 * k) for k in range(3)] +
                        [dicom_slice("2.25.99002", 0, 0, description="Scout")]))
    put("dicom_series", "refused-two-series-none-chosen.bin",
        SLICE_MARK.join([dicom_slice("2.25.5", k, 2.5 * k) for k in range(2)] +
                        [dicom_slice("2.25.6", 0, 0, description="Scout")]))
    put("dicom_series", "refused-truncated-slice.bin",
        SLICE_MARK.join(dicom_slice(uid, k, 2.5 * k, cut=6 if k == 1 else 0) for k in range(3)))
    put("dicom_series", "refused-missing-slice.bin",
        SLICE_MARK.join(dicom_slice(uid, k, 2.5 * k) for k in (0, 1, 3, 4)))
    put("dicom_series", "refused-duplicate-slice.bin",
        SLICE_MARK.join(dicom_slice(uid, k, 2.5 * k) for k in (0, 1, 1, 2)))
    put("dicom_series", "refused-header-cut.bin",
        SLICE_MARK.join([dicom_slice(uid, 0, 0), dicom_slice(uid, 1, 2.5)[:200]]))


GROUPS = {"images": lambda: images(), "segmentation": lambda: segmentation(),
          "markups": lambda: markups(), "csvs": lambda: csvs(), "area_mesh": lambda: area_mesh(),
          "small_variants": lambda: small_variants(), "float_nifti": lambda: float_nifti(),
          "dicom_series": lambda: dicom_series()}

if __name__ == "__main__":
    for group in sys.argv[1:] or list(GROUPS):
        GROUPS[group]()
