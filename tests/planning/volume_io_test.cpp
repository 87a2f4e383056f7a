// Tests of planning/volume_io: round trips through NIfTI, NRRD and MetaImage with an oblique,
// anisotropic grid; DICOM series folders; agreement with nibabel's RAS world coordinates; and a
// clean Error (naming the file) for every kind of bad input, with no partial output left behind.
#include "planning/imaging/volume_io.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "foundation/error.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/grids.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using test::expect_error_containing;
using test::oblique_geometry;

// The same grid with the third axis reversed: determinant -1 (as in many NIfTI files from
// radiological-convention scanners).
ImageGeometry reflected_geometry() {
  ImageGeometry g = oblique_geometry();
  g.direction.col(2) *= -1.0;
  return g;
}

// Distinct values per voxel, negative ones where T allows, and a fractional part for float.
template <typename T>
Volume<T> sample_volume(const ImageGeometry& g) {
  Volume<T> v(g);
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        if constexpr (std::is_same_v<T, uint8_t>) {
          v(i, j, k) = uint8_t((i * 37 + j * 11 + k * 53) % 256);
        } else if constexpr (std::is_floating_point_v<T>) {
          v(i, j, k) = T(i + 10 * j + 100 * k) - T(250.25);
        } else {
          v(i, j, k) = T((i - 3) * 1000 + j * 10 + k);
        }
      }
    }
  }
  return v;
}

// Every test works in its own fresh folder, removed afterwards.
class VolumeIoTest : public ::testing::Test {
 protected:
  std::string file(const std::string& name) const { return dir_.file(name); }

  // Names of everything in the test folder (hidden temporaries included), sorted.
  std::vector<std::string> folder_entries() const {
    std::vector<std::string> names;
    for (const auto& entry : fs::directory_iterator(dir_)) {
      names.push_back(entry.path().filename().string());
    }
    std::sort(names.begin(), names.end());
    return names;
  }

  void write_bytes(const std::string& name, const std::string& bytes) const {
    std::ofstream out(file(name), std::ios::binary);
    out << bytes;
    ASSERT_TRUE(out.good());
  }

  test::TemporaryFolder dir_;
};

void expect_geometry_near(const ImageGeometry& actual, const ImageGeometry& expected, double tol) {
  EXPECT_EQ(actual.dims, expected.dims);
  EXPECT_LT((actual.origin - expected.origin).cwiseAbs().maxCoeff(), tol)
      << "origin " << actual.origin.transpose() << " vs " << expected.origin.transpose();
  EXPECT_LT((actual.spacing - expected.spacing).cwiseAbs().maxCoeff(), tol)
      << "spacing " << actual.spacing.transpose() << " vs " << expected.spacing.transpose();
  EXPECT_LT((actual.direction - expected.direction).cwiseAbs().maxCoeff(), tol)
      << "direction\n"
      << actual.direction << "\nvs\n"
      << expected.direction;
}

template <typename T>
void expect_round_trip(const std::string& path, const ImageGeometry& geometry, double tol) {
  SCOPED_TRACE(path);
  const Volume<T> written = sample_volume<T>(geometry);
  write_volume(written, path);
  const Volume<T> read = read_volume<T>(path);
  expect_geometry_near(read.geometry(), geometry, tol);
  EXPECT_EQ(read.values(), written.values());  // stored in the file's own type: exact
}

// --- Round trips ------------------------------------------------------------------------------

struct Format {
  const char* extension;
  // NIfTI keeps origin, spacing and the direction (quaternion and sform) in float32: relative
  // error 6e-8 on values up to 41 mm gives < 3e-6 mm, so 1e-5. NRRD and MetaImage write decimal
  // text with 17 significant digits: 1e-9 leaves a wide margin over double rounding.
  double geometry_tol;
};

class RoundTrip : public VolumeIoTest, public ::testing::WithParamInterface<Format> {};

TEST_P(RoundTrip, KeepsValuesExactlyAndObliqueAnisotropicGeometry) {
  const Format format = GetParam();
  const ImageGeometry g = oblique_geometry();
  expect_round_trip<float>(file(std::string("f32") + format.extension), g, format.geometry_tol);
  expect_round_trip<int16_t>(file(std::string("i16") + format.extension), g, format.geometry_tol);
  expect_round_trip<uint8_t>(file(std::string("u8") + format.extension), g, format.geometry_tol);
  expect_round_trip<int32_t>(file(std::string("i32") + format.extension), g, format.geometry_tol);
}

TEST_P(RoundTrip, KeepsADirectionWithDeterminantMinusOne) {
  // NIfTI stores an improper rotation as a proper quaternion with qfac = -1 (third axis flipped)
  // and in the sform; ITK writes and reads both back, so the reflection survives in every format.
  const Format format = GetParam();
  const ImageGeometry g = reflected_geometry();
  ASSERT_NEAR(g.direction.determinant(), -1.0, 1e-12);
  expect_round_trip<float>(file(std::string("reflected") + format.extension), g,
                           format.geometry_tol);
}

TEST_P(RoundTrip, LeavesOnlyTheFinalFileInTheFolder) {
  const Format format = GetParam();
  const std::string name = std::string("plan") + format.extension;
  write_volume(sample_volume<float>(oblique_geometry()), file(name));
  EXPECT_EQ(folder_entries(), std::vector<std::string>{name});
  // Writing again replaces the file in place.
  write_volume(sample_volume<float>(oblique_geometry()), file(name));
  EXPECT_EQ(folder_entries(), std::vector<std::string>{name});
}

INSTANTIATE_TEST_SUITE_P(Formats, RoundTrip,
                         ::testing::Values(Format{".nii", 1e-5}, Format{".nii.gz", 1e-5},
                                           Format{".nrrd", 1e-9}, Format{".mha", 1e-9}),
                         [](const ::testing::TestParamInfo<Format>& info) {
                           std::string name = info.param.extension + 1;
                           std::replace(name.begin(), name.end(), '.', '_');
                           return name;
                         });

// --- Type conversion on read --------------------------------------------------------------------

TEST_F(VolumeIoTest, ReadConvertsToWiderTypesExactly) {
  const Volume<int16_t> written = sample_volume<int16_t>(oblique_geometry());
  write_volume(written, file("ct.nii.gz"));
  const Volume<double> as_double = read_volume<double>(file("ct.nii.gz"));
  const Volume<int32_t> as_int32 = read_volume<int32_t>(file("ct.nii.gz"));
  for (int64_t i = 0; i < written.voxel_count(); ++i) {
    ASSERT_EQ(as_double[i], double(written[i])) << "offset " << i;
    ASSERT_EQ(as_int32[i], int32_t(written[i])) << "offset " << i;
  }
}

TEST_F(VolumeIoTest, ReadRoundsFloatsToTheNearestInteger) {
  Volume<float> written(oblique_geometry(), 0.0f);
  written(1, 2, 3) = -999.7f;
  written(2, 2, 3) = 40.4f;
  write_volume(written, file("ct.nrrd"));
  const Volume<int16_t> read = read_volume<int16_t>(file("ct.nrrd"));
  EXPECT_EQ(read(1, 2, 3), -1000);
  EXPECT_EQ(read(2, 2, 3), 40);
}

TEST_F(VolumeIoTest, ReadRejectsValuesOutsideTheTargetTypeNamingTheVoxel) {
  Volume<int16_t> written(oblique_geometry(), 0);
  written(4, 1, 2) = -5;
  write_volume(written, file("ct.nii.gz"));
  expect_error_containing([&] { read_volume<uint8_t>(file("ct.nii.gz")); },
                          {"ct.nii.gz", "voxel (4, 1, 2)", "-5", "uint8"});
}

// --- Label maps and masks
// -------------------------------------------------------------------------

TEST_F(VolumeIoTest, LabelMapKeepsIntegerLabelsStoredAsFloat) {
  Volume<float> written(oblique_geometry(), 0.0f);
  written(1, 1, 1) = 7.0f;
  written(6, 4, 3) = 65535.0f;
  write_volume(written, file("labels.nii.gz"));
  const Volume<int32_t> labels = read_label_map(file("labels.nii.gz"));
  EXPECT_EQ(labels(1, 1, 1), 7);
  EXPECT_EQ(labels(6, 4, 3), 65535);
  EXPECT_EQ(labels(0, 0, 0), 0);
  expect_geometry_near(labels.geometry(), oblique_geometry(), 1e-5);
}

TEST_F(VolumeIoTest, LabelMapRejectsANonIntegerValueNamingTheVoxel) {
  Volume<float> written(oblique_geometry(), 1.0f);
  written(3, 1, 2) = 2.5f;
  write_volume(written, file("labels.nii.gz"));
  expect_error_containing([&] { read_label_map(file("labels.nii.gz")); },
                          {"labels.nii.gz", "voxel (3, 1, 2)", "2.5", "integer"});
}

TEST_F(VolumeIoTest, LabelMapRejectsNegativeAndTooLargeLabels) {
  Volume<int16_t> negative(oblique_geometry(), 0);
  negative(0, 3, 1) = -1;
  write_volume(negative, file("negative.nrrd"));
  expect_error_containing([&] { read_label_map(file("negative.nrrd")); },
                          {"negative.nrrd", "voxel (0, 3, 1)", "-1"});

  Volume<int32_t> large(oblique_geometry(), 0);
  large(5, 0, 0) = 70000;
  write_volume(large, file("large.mha"));
  expect_error_containing([&] { read_label_map(file("large.mha")); },
                          {"large.mha", "voxel (5, 0, 0)", "70000", "65535"});
}

TEST_F(VolumeIoTest, MaskIsOneExactlyWhereTheValueExceedsOneHalf) {
  Volume<float> written(oblique_geometry(), 0.0f);
  written(0, 0, 0) = 0.2f;
  written(1, 0, 0) = 0.5f;  // not above 0.5
  written(2, 0, 0) = 0.51f;
  written(3, 0, 0) = 3.0f;
  written(4, 0, 0) = -2.0f;
  write_volume(written, file("tumor.nii.gz"));
  const Volume<uint8_t> mask = read_mask(file("tumor.nii.gz"));
  EXPECT_EQ(mask(0, 0, 0), 0);
  EXPECT_EQ(mask(1, 0, 0), 0);
  EXPECT_EQ(mask(2, 0, 0), 1);
  EXPECT_EQ(mask(3, 0, 0), 1);
  EXPECT_EQ(mask(4, 0, 0), 0);
  int64_t ones = 0;
  for (const uint8_t v : mask.values()) ones += v;
  EXPECT_EQ(ones, 2);
}

// --- Non-finite voxels in NIfTI files -----------------------------------------------------------

// The message of the Error `f` throws; "no error" when it returns.
template <typename F>
std::string error_of(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "no error";
}

// A single-file NIfTI-1 (version 1) or NIfTI-2 (version 2) of float32 (datatype 16) or float64
// (64) voxels, written byte by byte: 1 mm voxels, no orientation codes, in little or big endian.
std::string hand_written_nifti(int version, bool big_endian, int datatype,
                               const std::vector<int64_t>& dims, const std::vector<double>& values) {
  const size_t header_size = version == 1 ? 348 : 540;
  const size_t vox_offset = header_size + 4;  // and 4 bytes of (no) extensions
  std::string bytes(vox_offset, '\0');
  const auto put = [&](size_t at, auto value) {
    char b[sizeof value];
    std::memcpy(b, &value, sizeof value);
    if (big_endian) std::reverse(b, b + sizeof value);
    std::memcpy(&bytes[at], b, sizeof value);
  };
  const int16_t bitpix = datatype == 16 ? 32 : 64;
  if (version == 1) {
    put(0, int32_t(348));
    put(40, int16_t(dims.size()));
    for (size_t d = 0; d < dims.size(); ++d) put(42 + 2 * d, int16_t(dims[d]));
    put(70, int16_t(datatype));
    put(72, bitpix);
    for (size_t d = 0; d < 8; ++d) put(76 + 4 * d, 1.0f);
    put(108, float(vox_offset));
    put(112, 1.0f);  // scl_slope
    std::memcpy(&bytes[344], "n+1", 4);
  } else {
    put(0, int32_t(540));
    std::memcpy(&bytes[4], "n+2\0\r\n\032\n", 8);
    put(12, int16_t(datatype));
    put(14, bitpix);
    put(16, int64_t(dims.size()));
    for (size_t d = 0; d < dims.size(); ++d) put(24 + 8 * d, int64_t(dims[d]));
    for (size_t d = 0; d < 8; ++d) put(104 + 8 * d, 1.0);
    put(168, int64_t(vox_offset));
    put(176, 1.0);  // scl_slope
  }
  for (const double v : values) {
    const size_t at = bytes.size();
    bytes.resize(at + size_t(bitpix / 8));
    if (datatype == 16) {
      put(at, float(v));
    } else {
      put(at, v);
    }
  }
  return bytes;
}

// niftilib sets NaN and infinite float voxels to 0 as it reads them: a label map, mask or CT with
// NaN voxels would plan as if they held 0 (background, safe) unless the file's own bytes are
// checked. The first bad voxel is named by its index, for every reader of a volume.
TEST_F(VolumeIoTest, NanInAFloatNiftiIsRefusedNamingTheVoxelForEveryReader) {
  Volume<float> v(oblique_geometry(), 1.0f);  // 7 x 5 x 4
  v(5, 3, 2) = std::numeric_limits<float>::quiet_NaN();
  v(6, 4, 3) = std::numeric_limits<float>::quiet_NaN();  // later in file order: not the first
  for (const std::string name : {"labels.nii.gz", "labels.nii"}) {
    SCOPED_TRACE(name);
    write_volume(v, file(name));
    const std::string expected = file(name) + ": voxel (5, 3, 2) has value nan (expected a finite number)";
    EXPECT_EQ(error_of([&] { read_label_map(file(name)); }), expected);
    EXPECT_EQ(error_of([&] { read_mask(file(name)); }), expected);
    EXPECT_EQ(error_of([&] { read_volume<float>(file(name)); }), expected);
    EXPECT_EQ(error_of([&] { read_volume<int16_t>(file(name)); }), expected);  // a CT
  }
}

TEST_F(VolumeIoTest, InfiniteFloatNiftiVoxelsAreRefusedNamingTheVoxel) {
  Volume<float> v(oblique_geometry(), 0.0f);
  v(0, 0, 0) = 2.0f;
  v(2, 1, 3) = -std::numeric_limits<float>::infinity();
  write_volume(v, file("blocking.nii.gz"));
  EXPECT_EQ(error_of([&] { read_volume<float>(file("blocking.nii.gz")); }),
            file("blocking.nii.gz") + ": voxel (2, 1, 3) has value -inf (expected a finite number)");
}

// Both byte orders, float32 and float64: voxel (1, 2, 0) of a 3 x 4 x 2 grid is the 7th value in
// file order (x fastest). NIfTI-2 files are refused whole by ITK 5.2's reader (nifti1_io), with
// or without bad voxels.
TEST_F(VolumeIoTest, NonFiniteVoxelsAreFoundInBigEndianAndFloat64NiftiFiles) {
  std::vector<double> values(24);
  for (size_t i = 0; i < values.size(); ++i) values[i] = double(i);
  write_bytes("v2.nii", hand_written_nifti(2, false, 16, {3, 4, 2}, values));
  expect_error_containing([&] { read_volume<float>(file("v2.nii")); }, {"v2.nii", "cannot read"});
  for (const int version : {1}) {
    for (const bool big_endian : {false, true}) {
      for (const int datatype : {16, 64}) {
        const std::string name = "v" + std::to_string(version) + (big_endian ? "be" : "le") +
                                 std::to_string(datatype) + ".nii";
        SCOPED_TRACE(name);
        write_bytes(name, hand_written_nifti(version, big_endian, datatype, {3, 4, 2}, values));
        const Volume<float> fine = read_volume<float>(file(name));  // all finite: read as stored
        ASSERT_EQ(fine.dims(), (Index3{3, 4, 2}));
        EXPECT_EQ(fine(1, 2, 0), 7.0f);
        EXPECT_EQ(fine(2, 3, 1), 23.0f);
        std::vector<double> bad = values;
        bad[7] = std::numeric_limits<double>::infinity();
        bad[20] = std::nan("");
        write_bytes(name, hand_written_nifti(version, big_endian, datatype, {3, 4, 2}, bad));
        EXPECT_EQ(error_of([&] { read_label_map(file(name)); }),
                  file(name) + ": voxel (1, 2, 0) has value inf (expected a finite number)");
      }
    }
  }
}

// A 4D file's phases are split through ITK as well: the phase and the voxel are named.
TEST_F(VolumeIoTest, NanInAPhaseOfA4DNiftiIsRefusedNamingThePhaseAndVoxel) {
  std::vector<Volume<float>> phases(3, Volume<float>(oblique_geometry(), 4.0f));
  phases[2](3, 0, 1) = std::numeric_limits<float>::quiet_NaN();
  for (const std::string name : {"ct4d.nii.gz", "ct4d.nii"}) {
    SCOPED_TRACE(name);
    write_volume_frames(phases, file(name));
    const std::vector<std::string> out = {file("p0.nii.gz"), file("p1.nii.gz"), file("p2.nii.gz")};
    EXPECT_EQ(error_of([&] { split_volume_frames(file(name), out); }),
              file(name) + ": phase 2, voxel (3, 0, 1) has value nan (expected a finite number)");
  }
  // A big-endian 4D file with one Inf in its second phase (2 x 2 x 1 x 2).
  write_bytes("be.nii", hand_written_nifti(1, true, 16, {2, 2, 1, 2},
                                           {0, 1, 2, 3, 4, 5, 6, HUGE_VAL}));
  EXPECT_EQ(error_of([&] { split_volume_frames(file("be.nii"), {file("a.nii"), file("b.nii")}); }),
            file("be.nii") + ": phase 1, voxel (1, 1, 0) has value inf (expected a finite number)");
}

// Integer data keep their fast path (no value check), and finite floats read as stored.
TEST_F(VolumeIoTest, IntegerAndFiniteFloatNiftiFilesReadAsStored) {
  Volume<int16_t> labels(oblique_geometry(), 0);
  labels(5, 3, 2) = -32768;  // the bit pattern of no float matters for integers
  labels(1, 1, 1) = 12;
  write_volume(labels, file("labels.nii.gz"));
  const Volume<int16_t> read = read_volume<int16_t>(file("labels.nii.gz"));
  EXPECT_EQ(read.values(), labels.values());
  Volume<float> ct(oblique_geometry(), -1000.0f);
  ct(5, 3, 2) = std::numeric_limits<float>::max();
  write_volume(ct, file("ct.nii.gz"));
  EXPECT_EQ(read_volume<float>(file("ct.nii.gz")).values(), ct.values());
}

// --- DICOM series -------------------------------------------------------------------------------

// Minimal DICOM Part 10 writer for the tests: CT Image Storage slices, explicit VR little endian,
// signed 16-bit pixels, slope 1, intercept 0. Written by hand (not through ITK) so the test reads
// files whose geometry tags we set ourselves.
class DicomSliceWriter {
 public:
  void string_element(uint16_t group, uint16_t element, const char* vr, std::string value) {
    if (value.size() % 2 != 0) value.push_back(std::strcmp(vr, "UI") == 0 ? '\0' : ' ');
    header(group, element, vr, uint32_t(value.size()));
    bytes_ += value;
  }
  void us_element(uint16_t group, uint16_t element, uint16_t value) {
    header(group, element, "US", 2);
    put16(value);
  }
  void ob_element(uint16_t group, uint16_t element, const char* vr, const std::string& value) {
    header(group, element, vr, uint32_t(value.size()));
    bytes_ += value;
  }
  const std::string& bytes() const { return bytes_; }
  size_t size() const { return bytes_.size(); }

 private:
  void put16(uint16_t v) {
    bytes_.push_back(char(v & 0xff));
    bytes_.push_back(char(v >> 8));
  }
  void put32(uint32_t v) {
    put16(uint16_t(v & 0xffff));
    put16(uint16_t(v >> 16));
  }
  void header(uint16_t group, uint16_t element, const char* vr, uint32_t length) {
    put16(group);
    put16(element);
    bytes_.append(vr, 2);
    const bool long_form = std::strcmp(vr, "OB") == 0 || std::strcmp(vr, "OW") == 0;
    if (long_form) {
      put16(0);
      put32(length);
    } else {
      put16(uint16_t(length));
    }
  }
  std::string bytes_;
};

// Decimal strings (DS) hold at most 16 characters: 10 significant digits fit and give 1e-10 mm.
std::string ds(std::initializer_list<double> values) {
  std::string out;
  for (const double v : values) {
    char buffer[32];
    std::snprintf(buffer, sizeof buffer, "%.10g", v);
    if (!out.empty()) out += '\\';
    out += buffer;
  }
  return out;
}

// Writes the volume as one DICOM file per k-slice, files named in reverse slice order so that the
// reader has to sort by position. The index axes must be (row direction, column direction,
// row x column), as DICOM readers derive the slice axis from the orientation.
void write_dicom_series(const Volume<int16_t>& volume, const fs::path& folder,
                        const std::string& series_uid, int series_number,
                        const std::string& description = "", int first_instance = 1) {
  const ImageGeometry& g = volume.geometry();
  const Eigen::Vector3d row = g.direction.col(0);
  const Eigen::Vector3d col = g.direction.col(1);
  const std::string sop_class = "1.2.840.10008.5.1.4.1.1.2";  // CT Image Storage
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    const std::string sop_instance = series_uid + "." + std::to_string(k + first_instance);
    const Eigen::Vector3d position = g.index_to_physical(0, 0, k);
    std::string pixels;
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        const uint16_t v = uint16_t(volume(i, j, k));
        pixels.push_back(char(v & 0xff));
        pixels.push_back(char(v >> 8));
      }
    }
    DicomSliceWriter meta;
    meta.ob_element(0x0002, 0x0001, "OB", std::string("\0\1", 2));
    meta.string_element(0x0002, 0x0002, "UI", sop_class);
    meta.string_element(0x0002, 0x0003, "UI", sop_instance);
    meta.string_element(0x0002, 0x0010, "UI", "1.2.840.10008.1.2.1");  // explicit VR LE
    meta.string_element(0x0002, 0x0012, "UI", "2.25.1234567890");
    DicomSliceWriter data;
    data.string_element(0x0008, 0x0016, "UI", sop_class);
    data.string_element(0x0008, 0x0018, "UI", sop_instance);
    data.string_element(0x0008, 0x0060, "CS", "CT");
    if (!description.empty()) data.string_element(0x0008, 0x103E, "LO", description);
    data.string_element(0x0010, 0x0010, "PN", "Phantom^Test");
    data.string_element(0x0010, 0x0020, "LO", "TEST-1");
    data.string_element(0x0018, 0x0050, "DS", ds({g.spacing[2]}));
    data.string_element(0x0020, 0x000D, "UI", "2.25.1234567891");
    data.string_element(0x0020, 0x000E, "UI", series_uid);
    data.string_element(0x0020, 0x0011, "IS", std::to_string(series_number));
    data.string_element(0x0020, 0x0013, "IS", std::to_string(k + 1));
    data.string_element(0x0020, 0x0032, "DS", ds({position.x(), position.y(), position.z()}));
    data.string_element(0x0020, 0x0037, "DS",
                        ds({row.x(), row.y(), row.z(), col.x(), col.y(), col.z()}));
    data.string_element(0x0020, 0x0052, "UI", "2.25.1234567892");
    data.us_element(0x0028, 0x0002, 1);
    data.string_element(0x0028, 0x0004, "CS", "MONOCHROME2");
    data.us_element(0x0028, 0x0010, uint16_t(g.dims[1]));  // rows = j
    data.us_element(0x0028, 0x0011, uint16_t(g.dims[0]));  // columns = i
    // Pixel spacing is (between rows, between columns) = (spacing j, spacing i).
    data.string_element(0x0028, 0x0030, "DS", ds({g.spacing[1], g.spacing[0]}));
    data.us_element(0x0028, 0x0100, 16);
    data.us_element(0x0028, 0x0101, 16);
    data.us_element(0x0028, 0x0102, 15);
    data.us_element(0x0028, 0x0103, 1);  // signed
    data.string_element(0x0028, 0x1052, "DS", "0");
    data.string_element(0x0028, 0x1053, "DS", "1");
    data.ob_element(0x7FE0, 0x0010, "OW", pixels);

    // (0002,0000) UL: length of the rest of the meta group.
    std::string file_bytes(128, '\0');
    file_bytes += "DICM";
    const uint32_t meta_length = uint32_t(meta.size());
    file_bytes += std::string("\x02\x00\x00\x00UL\x04\x00", 8);
    for (int b = 0; b < 4; ++b) file_bytes.push_back(char((meta_length >> (8 * b)) & 0xff));
    file_bytes += meta.bytes();
    file_bytes += data.bytes();
    const fs::path name =
        folder / ("s" + std::to_string(series_number) + "-" + std::to_string(100 - k) + ".dcm");
    std::ofstream out(name, std::ios::binary);
    out << file_bytes;
  }
}

// A folder of two series (a scout beside the CT) is refused with both listed; a chosen UID reads
// that series, with its own grid and values.
TEST_F(VolumeIoTest, DicomFolderWithTwoSeriesIsRefusedUntilOneIsChosen) {
  const ImageGeometry g = oblique_geometry();  // a proper rotation: slice axis = row x column
  ASSERT_LT((g.direction.col(0).cross(g.direction.col(1)) - g.direction.col(2)).norm(), 1e-12);
  const Volume<int16_t> ct = sample_volume<int16_t>(g);
  write_dicom_series(ct, dir_, "2.25.99001", 1, "Abdomen");
  ImageGeometry small = g;
  small.dims[2] = 2;
  write_dicom_series(Volume<int16_t>(small, 123), dir_, "2.25.99002", 2, "Scout");

  const std::string listed = dir_.string() +
                             " holds 2 DICOM series: 2.25.99001 (4 slices, CT 'Abdomen'), "
                             "2.25.99002 (2 slices, CT 'Scout'); choose one with --series UID";
  EXPECT_EQ(error_of([&] { read_volume<int16_t>(dir_.string()); }), listed);
  EXPECT_EQ(error_of([&] { read_volume_geometry(dir_.string()); }), listed);
  EXPECT_EQ(error_of([&] { read_label_map(dir_.string(), {{"2.25.123"}}); }), listed);

  const Volume<int16_t> read = read_volume<int16_t>(dir_.string(), {{"2.25.99001"}});
  // DICOM geometry passes through 10-digit decimal strings and the slice spacing is derived from
  // slice positions: 1e-3 mm is far above that rounding and far below any real error.
  expect_geometry_near(read.geometry(), g, 1e-3);
  EXPECT_EQ(read.values(), ct.values());
  // Another folder's UID listed beside it does not matter: UIDs are unique.
  const Volume<int32_t> scout = read_label_map(dir_.string(), {{"1.2.3", "2.25.99002"}});
  EXPECT_EQ(scout.dims(), (Index3{7, 5, 2}));
  EXPECT_TRUE(std::all_of(scout.values().begin(), scout.values().end(),
                          [](int32_t v) { return v == 123; }));
  expect_geometry_near(read_volume_geometry(dir_.string(), {{"2.25.99002"}}), small, 1e-3);
}

// The files of one CT series, 7 x 5 pixels, 2.1 mm apart: s1-100.dcm (k = 0) to s1-96.dcm.
class DicomSeriesTest : public VolumeIoTest {
 protected:
  void SetUp() override {
    ImageGeometry g = oblique_geometry();
    g.dims[2] = 5;
    write_dicom_series(sample_volume<int16_t>(g), dir_, "2.25.99001", 1);
    ASSERT_NO_THROW(read_volume<int16_t>(dir_.string()));
  }
  std::string folder() const { return dir_.string(); }
};

// ITK's series reader fills the missing end of a slice with zeros.
TEST_F(DicomSeriesTest, TruncatedSliceIsRefusedNamingIt) {
  fs::resize_file(dir_ / "s1-98.dcm", fs::file_size(dir_ / "s1-98.dcm") - 10);
  EXPECT_EQ(error_of([&] { read_volume<int16_t>(folder()); }),
            folder() + ": slice s1-98.dcm is truncated: its pixel data hold 60 bytes, expected 70 "
                       "(5 rows x 7 columns x 16 bits x 1 samples)");
}

// ITK bridges a missing slice as if the spacing were even (only a warning printed).
TEST_F(DicomSeriesTest, MissingSliceIsRefusedNamingTheGap) {
  fs::remove(dir_ / "s1-98.dcm");
  EXPECT_EQ(error_of([&] { read_volume<float>(folder()); }),
            folder() + ": slices s1-99.dcm and s1-97.dcm are 4.2 mm apart along the slice normal, "
                       "expected 2.1 mm (the series' usual spacing, within 0.021 mm): a missing "
                       "slice");
}

TEST_F(DicomSeriesTest, DuplicateSliceIsRefusedNamingBothFiles) {
  fs::copy_file(dir_ / "s1-98.dcm", dir_ / "copy.dcm");
  EXPECT_EQ(error_of([&] { read_mask(folder()); }),
            folder() + ": slices copy.dcm and s1-98.dcm are the same slice (SOPInstanceUID "
                       "2.25.99001.3): a duplicate");
  fs::remove(dir_ / "copy.dcm");
  // The same position under another SOPInstanceUID (exported twice).
  ImageGeometry g = oblique_geometry();
  g.dims[2] = 5;
  fs::create_directory(dir_ / "again");
  write_dicom_series(sample_volume<int16_t>(g), dir_ / "again", "2.25.99001", 2, "", 101);
  fs::copy_file(dir_ / "again" / "s2-98.dcm", dir_ / "s2-98.dcm");
  EXPECT_EQ(error_of([&] { read_volume<int16_t>(folder()); }),
            folder() + ": slices s1-98.dcm and s2-98.dcm lie at the same position (0 mm apart "
                       "along the slice normal): a duplicate slice");
}

TEST_F(DicomSeriesTest, UnreadableSliceIsRefusedNamingItNotACrash) {
  write_bytes("notes.txt", "no images here\n");
  EXPECT_EQ(error_of([&] { read_volume<int16_t>(folder()); }),
            folder() + ": slice notes.txt is not a readable DICOM file (not a DICOM Part 10 file "
                       "(no \"DICM\" at byte 128))");
  fs::remove(dir_ / "notes.txt");
  // Cut inside its header: GDCM itself would abort on an assertion here.
  fs::resize_file(dir_ / "s1-98.dcm", 200);
  expect_error_containing([&] { read_volume<int16_t>(folder()); },
                          {folder() + ": slice s1-98.dcm is not a readable DICOM file"});
  fs::resize_file(dir_ / "s1-98.dcm", 420);
  expect_error_containing([&] { read_volume_geometry(folder()); },
                          {folder() + ": slice s1-98.dcm is not a readable DICOM file"});
}

TEST_F(VolumeIoTest, FolderWithoutDicomFilesThrowsNamingTheFolder) {
  write_bytes("notes.txt", "no images here\n");
  expect_error_containing([&] { read_volume<int16_t>(dir_.string()); }, {dir_.string(), "DICOM"});
}

// --- nibabel agrees on the world position -------------------------------------------------------

constexpr const char* kPython = "/usr/bin/python3";

// Runs `script` with /usr/bin/python3 and `argument`; returns its standard output, empty when it
// fails.
std::string run_python(const std::string& script, const std::string& argument) {
  std::string output;
  const std::string command = std::string(kPython) + " -c '" + script + "' " + argument;
  FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) return output;
  std::array<char, 256> buffer{};
  while (std::fgets(buffer.data(), int(buffer.size()), pipe) != nullptr) output += buffer.data();
  return ::pclose(pipe) == 0 ? output : std::string();
}

bool nibabel_available() {
  return fs::exists(kPython) &&
         std::system(
             (std::string(kPython) + " -c 'import nibabel, numpy' > /dev/null 2>&1").c_str()) == 0;
}

TEST_F(VolumeIoTest, NibabelFindsTheMarkedVoxelAtTheSamePointInRas) {
  const ImageGeometry g = reflected_geometry();  // the harder case: determinant -1
  Volume<uint8_t> volume(g, 0);
  volume(5, 1, 3) = 200;
  const std::string path = file("marker.nii.gz");
  write_volume(volume, path);

  // nibabel finds the voxel itself (checks the data order) and maps it with the affine (RAS).
  const std::string script =
      "import sys, nibabel, numpy\n"
      "img = nibabel.load(sys.argv[1])\n"
      "i, j, k = numpy.argwhere(numpy.asanyarray(img.dataobj) == 200)[0]\n"
      "x, y, z, _ = img.affine @ [i, j, k, 1]\n"
      "print(i, j, k, repr(float(x)), repr(float(y)), repr(float(z)))\n";
  const std::string output = run_python(script, path);
  if (output.empty() && !nibabel_available()) {
    GTEST_SKIP() << kPython << " with nibabel and numpy is not available";
  }
  ASSERT_FALSE(output.empty()) << "nibabel script failed";
  std::istringstream in(output);
  int64_t i = -1, j = -1, k = -1;
  Eigen::Vector3d ras;
  in >> i >> j >> k >> ras.x() >> ras.y() >> ras.z();
  ASSERT_TRUE(bool(in)) << "cannot parse: " << output;
  EXPECT_EQ((Index3{i, j, k}), (Index3{5, 1, 3}));

  const Eigen::Vector3d lps = g.index_to_physical(5, 1, 3);
  const Eigen::Vector3d expected_ras(-lps.x(), -lps.y(), lps.z());
  // float32 header values (see Format) keep the point within 1e-4 mm; we promise 1e-3 mm.
  EXPECT_LT((ras - expected_ras).cwiseAbs().maxCoeff(), 1e-3)
      << "nibabel RAS " << ras.transpose() << ", ours (LPS->RAS) " << expected_ras.transpose();
}

TEST_F(VolumeIoTest, NiftiScaleAndInterceptFromNibabelAreApplied) {
  // int16 stored values v = i + 10 j + 100 k with scl_slope 2, scl_inter -1024: value 2 v - 1024.
  const std::string path = file("scaled.nii.gz");
  const std::string script =
      "import sys, nibabel, numpy\n"
      "i, j, k = numpy.indices((4, 3, 2))\n"
      "img = nibabel.Nifti1Image((i + 10 * j + 100 * k).astype(numpy.int16), numpy.eye(4))\n"
      "img.header.set_slope_inter(2.0, -1024.0)\n"
      "nibabel.save(img, sys.argv[1])\n"
      "print(\"saved\")\n";
  if (run_python(script, path).empty()) {
    if (!nibabel_available()) GTEST_SKIP() << kPython << " with nibabel and numpy is not available";
    FAIL() << "nibabel could not write " << path;
  }
  const Volume<float> v = read_volume<float>(path);
  ASSERT_EQ(v.dims(), (Index3{4, 3, 2}));
  EXPECT_EQ(v(0, 0, 0), -1024.0f);
  EXPECT_EQ(v(3, 2, 1), 2.0f * (3 + 20 + 100) - 1024.0f);
  EXPECT_EQ(read_volume<int16_t>(path)(3, 2, 1), 2 * (3 + 20 + 100) - 1024);
}

// --- Bad input ----------------------------------------------------------------------------------

TEST_F(VolumeIoTest, MissingFileThrowsNamingIt) {
  expect_error_containing([&] { read_volume<float>(file("ct.nii.gz")); },
                          {"ct.nii.gz", "does not exist"});
}

TEST_F(VolumeIoTest, TextFileNamedNiftiThrowsNamingIt) {
  write_bytes("ct.nii.gz", "this is not an image\n");
  expect_error_containing([&] { read_volume<float>(file("ct.nii.gz")); },
                          {"ct.nii.gz", "cannot read"});
}

TEST_F(VolumeIoTest, TruncatedFileThrowsNamingIt) {
  // ITK's NIfTI reader fills a short read with zeros without an error; read_volume checks the
  // length itself. NRRD and MetaImage readers report short data on their own.
  ImageGeometry g = oblique_geometry();
  g.dims = {40, 40, 40};
  for (const std::string name : {"ct.nii.gz", "ct.nii", "ct.nrrd", "ct.mha"}) {
    SCOPED_TRACE(name);
    write_volume(sample_volume<float>(g), file(name));
    fs::resize_file(file(name), fs::file_size(file(name)) / 2);
    expect_error_containing([&] { read_volume<float>(file(name)); }, {name, "cannot read"});
  }
}

// A hand-written NRRD header with attached raw data (int16, little endian).
std::string nrrd(const std::string& fields, size_t voxel_count) {
  return "NRRD0004\ntype: short\nencoding: raw\nendian: little\n" + fields + "\n" +
         std::string(voxel_count * 2, '\0');
}

TEST_F(VolumeIoTest, TruncatedUncompressedNrrdAndMetaImageThrow) {
  // 2 x 2 x 2 int16 needs 16 bytes of data; both files hold 10.
  write_bytes("short.nrrd", nrrd("dimension: 3\nsizes: 2 2 2\n", 5));
  expect_error_containing([&] { read_volume<float>(file("short.nrrd")); },
                          {"short.nrrd", "cannot read"});
  write_bytes("short.mha",
              "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_SHORT\n"
              "ElementDataFile = LOCAL\n" +
                  std::string(10, '\0'));
  expect_error_containing([&] { read_volume<float>(file("short.mha")); },
                          {"short.mha", "cannot read"});
}

// A CT beside label maps gives only its grid (the scan's coverage): from the header alone, the
// same grid read_volume gives, refused as read_volume refuses it.
TEST_F(VolumeIoTest, GeometryFromTheHeaderIsTheVolumesGrid) {
  for (const ImageGeometry& g : {oblique_geometry(), reflected_geometry()}) {
    for (const std::string name : {"ct.nii.gz", "ct.nrrd", "ct.mha"}) {
      write_volume(sample_volume<int16_t>(g), file(name));
      const ImageGeometry header = read_volume_geometry(file(name));
      const ImageGeometry full = read_volume<float>(file(name)).geometry();
      EXPECT_EQ(header.dims, full.dims) << name;
      EXPECT_TRUE(header.same_grid(full, 1e-12)) << name;
      EXPECT_TRUE(header.same_grid(g, 1e-5)) << name;
    }
  }
  write_bytes("slice.nrrd", nrrd("dimension: 2\nsizes: 4 3\nspacings: 1 1\n", 12));
  expect_error_containing([&] { read_volume_geometry(file("slice.nrrd")); }, {"slice.nrrd", "2D"});
  expect_error_containing([&] { read_volume_geometry(file("none.nii.gz")); },
                          {"none.nii.gz", "does not exist"});
}

// Plans read several files at once (a breathing plan's phases side by side, a tumor beside the
// label map), and ITK's reads take turns (image_read_mutex: a breathing plan reading its phases
// side by side aborted in "malloc(): unaligned tcache chunk" inside
// NiftiImageIO::ReadImageInformation on the GPU machine). Reads of the three formats on eight
// threads must each give the file's own grid and labels.
TEST_F(VolumeIoTest, FilesReadOnManyThreadsAtOnceAreEachTheirOwnVolume) {
  std::vector<std::string> names;
  std::vector<Volume<int32_t>> expected;
  ImageGeometry grids[] = {oblique_geometry(), reflected_geometry()};
  for (ImageGeometry& g : grids) g.dims = {64, 48, 40};  // a few hundred KB a file
  int n = 0;
  for (const std::string ext : {".nii.gz", ".nii", ".nrrd", ".mha"}) {
    for (int copy = 0; copy < 3; ++copy, ++n) {
      Volume<int32_t> v = sample_volume<int32_t>(grids[n % 2]);
      for (size_t i = 0; i < v.values().size(); ++i) {
        v.values()[i] = int32_t((i * 7 + size_t(n)) % 97);  // every file its own labels
      }
      names.push_back(file("labels" + std::to_string(n) + ext));
      write_volume(v, names.back());
      expected.push_back(std::move(v));
    }
  }
  std::atomic<int> wrong{0}, failed{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 8; ++t) {
    threads.emplace_back([&, t] {
      for (int round = 0; round < 40; ++round) {
        const size_t f = size_t(t * 5 + round * 3) % names.size();
        try {
          const ImageGeometry header = read_volume_geometry(names[f]);
          const Volume<int32_t> v = read_label_map(names[f]);
          if (!header.same_grid(expected[f].geometry(), 1e-5) ||
              v.values() != expected[f].values()) {
            ++wrong;
          }
        } catch (const std::exception& e) {
          if (failed++ == 0) ADD_FAILURE() << e.what();
        }
      }
    });
  }
  for (std::thread& t : threads) t.join();
  EXPECT_EQ(wrong.load(), 0);
  EXPECT_EQ(failed.load(), 0);
}

TEST_F(VolumeIoTest, TwoDimensionalImageThrowsNamingIt) {
  write_bytes("slice.nrrd", nrrd("dimension: 2\nsizes: 4 3\nspacings: 1 1\n", 12));
  expect_error_containing([&] { read_volume<float>(file("slice.nrrd")); }, {"slice.nrrd", "2D"});
}

TEST_F(VolumeIoTest, FourDimensionalImageWithSeveralVolumesThrows) {
  write_bytes("dwi.nrrd", nrrd("dimension: 4\nsizes: 3 3 3 2\nspacings: 1 2 3 1\n", 54));
  expect_error_containing([&] { read_volume<float>(file("dwi.nrrd")); }, {"dwi.nrrd", "4D"});
}

TEST_F(VolumeIoTest, FourDimensionalImageWithOneVolumeReadsAs3D) {
  write_bytes("one.nrrd", nrrd("dimension: 4\nsizes: 3 4 5 1\nspacings: 1 2 3 1\n", 60));
  const Volume<float> v = read_volume<float>(file("one.nrrd"));
  EXPECT_EQ(v.dims(), (Index3{3, 4, 5}));
  EXPECT_EQ(v.geometry().spacing, Eigen::Vector3d(1, 2, 3));
}

TEST_F(VolumeIoTest, VectorPixelsThrowNamingTheFile) {
  write_bytes("field.nrrd",
              nrrd("dimension: 4\nsizes: 3 2 2 2\nkinds: vector domain domain domain\n", 24));
  expect_error_containing([&] { read_volume<float>(file("field.nrrd")); },
                          {"field.nrrd", "3 components"});
}

TEST_F(VolumeIoTest, ZeroSpacingInTheHeaderThrowsNamingTheFile) {
  write_bytes("flat.nrrd", nrrd("dimension: 3\nsizes: 2 2 2\nspacings: 0 1 1\n", 8));
  expect_error_containing([&] { read_volume<float>(file("flat.nrrd")); }, {"flat.nrrd", "spacing"});
}

TEST_F(VolumeIoTest, ZeroSpaceDirectionColumnThrowsNamingTheFile) {
  write_bytes("flat.nrrd", nrrd("dimension: 3\nspace: left-posterior-superior\nsizes: 2 2 2\n"
                                "space directions: (0,0,0) (0,1,0) (0,0,1)\n"
                                "space origin: (0,0,0)\n",
                                8));
  expect_error_containing([&] { read_volume<float>(file("flat.nrrd")); }, {"flat.nrrd"});
}

TEST_F(VolumeIoTest, NegativeSpacingThrowsNamingTheFile) {
  write_bytes("flipped.nrrd", nrrd("dimension: 3\nsizes: 2 2 2\nspacings: 1 -1 1\n", 8));
  expect_error_containing([&] { read_volume<float>(file("flipped.nrrd")); },
                          {"flipped.nrrd", "spacing"});
}

TEST_F(VolumeIoTest, NonOrthogonalDirectionsThrowNamingTheFile) {
  write_bytes("sheared.nrrd", nrrd("dimension: 3\nspace: left-posterior-superior\nsizes: 2 2 2\n"
                                   "space directions: (1,0,0) (1,1,0) (0,0,1)\n"
                                   "space origin: (0,0,0)\n",
                                   8));
  expect_error_containing([&] { read_volume<float>(file("sheared.nrrd")); },
                          {"sheared.nrrd", "direction"});
}

// Header values ITK would abort on (vnl asserts finite matrices) or replace in silence are
// refused, naming the file and the field, before ITK reads the header.
TEST_F(VolumeIoTest, NonFiniteOrZeroNiftiHeaderFieldsAreRefusedNotCrashes) {
  write_volume(Volume<float>(oblique_geometry(), 1.0f), file("good.nii"));
  std::string bytes;
  {
    std::ifstream in(file("good.nii"), std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    bytes = ss.str();
  }
  ASSERT_GT(bytes.size(), 348u);
  const auto patched = [&](size_t at, float value) {
    std::string b = bytes;
    std::memcpy(&b[at], &value, 4);
    return b;
  };
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  write_bytes("nan_sform.nii", patched(280 + 12, nan));  // srow_x[3]: the origin's x
  expect_error_containing([&] { read_volume<float>(file("nan_sform.nii")); },
                          {"nan_sform.nii", "srow_x[3]", "finite"});
  write_bytes("nan_qoffset.nii", patched(268, nan));
  expect_error_containing([&] { read_volume<float>(file("nan_qoffset.nii")); },
                          {"nan_qoffset.nii", "qoffset_x"});
  write_bytes("inf_quatern.nii", patched(256, inf));
  expect_error_containing([&] { read_volume<float>(file("inf_quatern.nii")); },
                          {"inf_quatern.nii", "quatern_b"});
  for (const float pixdim : {0.0f, nan, inf, -1.0f}) {
    write_bytes("pixdim.nii", patched(76 + 4 * 2, pixdim));  // pixdim[2]
    expect_error_containing([&] { read_volume<float>(file("pixdim.nii")); },
                            {"pixdim.nii", "pixdim[2]", "voxel size"});
  }
  EXPECT_NO_THROW(read_volume<float>(file("good.nii")));
}

TEST_F(VolumeIoTest, NonFiniteNrrdAndMetaImageHeadersAreRefusedNotCrashes) {
  write_bytes("nan.nrrd", nrrd("dimension: 3\nspace: left-posterior-superior\nsizes: 2 2 2\n"
                               "space directions: (1,0,0) (0,nan,0) (0,0,1)\n"
                               "space origin: (0,0,0)\n",
                               8));
  expect_error_containing([&] { read_volume<float>(file("nan.nrrd")); },
                          {"nan.nrrd", "space directions", "nan"});
  write_bytes("inf.nrrd", nrrd("dimension: 3\nspace: left-posterior-superior\nsizes: 2 2 2\n"
                               "space directions: (1,0,0) (0,1,0) (0,0,1)\n"
                               "space origin: (0,inf,0)\n",
                               8));
  expect_error_containing([&] { read_volume<float>(file("inf.nrrd")); },
                          {"inf.nrrd", "space origin"});
  write_bytes("nan.mha",
              "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementSpacing = nan 1 1\n"
              "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
                  std::string(8, '\0'));
  expect_error_containing([&] { read_volume<float>(file("nan.mha")); },
                          {"nan.mha", "ElementSpacing"});
  write_bytes("offset.mha",
              "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nOffset = 0 0 -inf\n"
              "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" +
                  std::string(8, '\0'));
  expect_error_containing([&] { read_volume<float>(file("offset.mha")); },
                          {"offset.mha", "Offset"});
}

// A 512-byte NRRD declaring 10^13 voxels is refused from its header, before any allocation.
TEST_F(VolumeIoTest, NrrdDeclaringMoreVoxelsThanItHoldsIsRefusedAtOnce) {
  write_bytes("huge.nrrd", nrrd("dimension: 3\nsizes: 100000 100000 1000\n", 200));
  const auto t0 = std::chrono::steady_clock::now();
  expect_error_containing([&] { read_volume<float>(file("huge.nrrd")); },
                          {"huge.nrrd", "sizes", "voxels"});
  EXPECT_LT(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), 1.0);
  write_bytes("huge_gz.nrrd",
              nrrd("dimension: 3\nsizes: 100000 100000 1000\nencoding: gzip\n", 200));
  expect_error_containing([&] { read_volume<float>(file("huge_gz.nrrd")); },
                          {"huge_gz.nrrd", "sizes"});
}

TEST_F(VolumeIoTest, WritingIntoAMissingFolderThrowsAndCreatesNothing) {
  const std::string path = (dir_ / "missing" / "out.nii.gz").string();
  expect_error_containing([&] { write_volume(sample_volume<float>(oblique_geometry()), path); },
                          {"out.nii.gz", "does not exist"});
  EXPECT_TRUE(folder_entries().empty());
}

TEST_F(VolumeIoTest, FailedRenameLeavesNoTemporary) {
  // The final name is taken by a folder: ITK writes the temporary, the rename fails.
  fs::create_directory(dir_ / "out.nii.gz");
  expect_error_containing(
      [&] { write_volume(sample_volume<float>(oblique_geometry()), file("out.nii.gz")); },
      {"out.nii.gz"});
  EXPECT_EQ(folder_entries(), std::vector<std::string>{"out.nii.gz"});
  EXPECT_TRUE(fs::is_directory(dir_ / "out.nii.gz"));
}

TEST_F(VolumeIoTest, FailedItkWriteThrowsCleanErrorAndLeavesNothing) {
  // About 250 characters is a legal file name, but the temporary sibling's longer name is not:
  // the format library itself fails to create the file. (NIfTI only prints that; NRRD throws
  // std::bad_alloc; MetaImage throws an ITK exception: each must become one clean Error.)
  for (const std::string extension : {".nii.gz", ".nii", ".nrrd", ".mha"}) {
    const std::string name = std::string(250 - extension.size(), 'v') + extension;
    SCOPED_TRACE(extension);
    expect_error_containing(
        [&] { write_volume(sample_volume<float>(oblique_geometry()), file(name)); },
        {name, "cannot write"});
    EXPECT_TRUE(folder_entries().empty());
  }
}

TEST_F(VolumeIoTest, UnsupportedExtensionOrBadGeometryIsNotWritten) {
  expect_error_containing(
      [&] { write_volume(sample_volume<float>(oblique_geometry()), file("out.png")); },
      {"out.png", "extension"});
  ImageGeometry flat = oblique_geometry();
  flat.spacing[0] = 0.0;
  expect_error_containing([&] { write_volume(Volume<float>(flat), file("flat.nii.gz")); },
                          {"flat.nii.gz", "spacing"});
  EXPECT_TRUE(folder_entries().empty());
}

}  // namespace
}  // namespace crepuscular::planning
