// PLUS sequence files (tests/data/plus-sequence-files, from the PLUS toolkit's own test data):
// frame counts, transforms, statuses and timestamps against the header's own text (read here
// line by line with a regular expression, not by the reader's parser); image frames decompressed
// to their sizes; a round trip through the writer gives the same sequence field for field and
// pixel for pixel; broken files are refused naming the file and the problem.
#include "recordings/plus_sequence.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>

#include "foundation/error.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::recordings {
namespace {

std::string data(const std::string& name) {
  return std::string(CREPUSCULAR_TEST_DATA) + "/plus-sequence-files/" + name;
}

std::string slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

// The header's per-frame lines, "Seq_FrameNNNN_Name = value" (MetaImage) or ":=" (NRRD), up to
// the data: frame -> name -> value text.
std::map<int, std::map<std::string, std::string>> header_frames(const std::string& path) {
  const std::string text = slurp(path);
  const size_t end = std::min(text.find("ElementDataFile"), text.find("\n\n"));
  std::istringstream in(text.substr(0, end));
  std::map<int, std::map<std::string, std::string>> frames;
  const std::regex line(R"(^Seq_Frame(\d{4})_(\w+)\s*(?:=|:=)\s*(.*?)\s*$)");
  std::string l;
  while (std::getline(in, l)) {
    std::smatch m;
    if (std::regex_match(l, m, line)) frames[std::stoi(m[1])][m[2]] = m[3];
  }
  return frames;
}

// Every frame's timestamp, transforms (16 numbers each) and statuses equal the header's text.
void expect_matches_header(const PlusSequence& s, const std::string& path) {
  const auto text = header_frames(path);
  ASSERT_EQ(s.frames.size(), text.size()) << path;
  for (const auto& [f, fields] : text) {
    const PlusFrame& frame = s.frames[size_t(f)];
    EXPECT_EQ(frame.fields.size(), fields.size()) << "frame " << f;
    for (const auto& [name, value] : fields) {
      EXPECT_EQ(frame.field(name), value) << "frame " << f << " " << name;
      if (name == "Timestamp") {
        EXPECT_EQ(frame.timestamp_s, std::stod(value)) << "frame " << f;
      }
      const std::string transform = plus_transform_name(name);
      if (transform.empty()) continue;
      ASSERT_TRUE(frame.transforms.count(transform)) << "frame " << f << " " << name;
      std::istringstream numbers(value);
      for (int k = 0; k < 16; ++k) {
        double v = 0;
        numbers >> v;
        EXPECT_EQ(frame.transforms.at(transform).matrix(k / 4, k % 4), v) << f << " " << name;
      }
      const auto status = fields.find(transform + "TransformStatus");
      EXPECT_EQ(frame.transforms.at(transform).valid,
                status == fields.end() || status->second == "OK")
          << "frame " << f << " " << name;
    }
  }
}

TEST(PlusSequence, TrackerSequenceOf500FramesMatchesItsHeader) {
  const std::string path = data("TransformInterpolationTest.igs.mha");
  const PlusSequence s = read_plus_sequence(path);
  EXPECT_EQ(s.frames.size(), 500u);
  expect_matches_header(s, path);
  // Probe and reference tracked; "Stylus" (16 numbers, but no "<From>To<To>Transform" name) is a
  // field as PLUS reads it, not a transform.
  EXPECT_EQ(s.transform_names(),
            (std::vector<std::string>{"ProbeToTracker", "ReferenceToTracker"}));
  EXPECT_EQ(s.frames[1].field("Stylus").substr(0, 10), "-0.0809767");
  EXPECT_EQ(s.width, 1);
  EXPECT_EQ(s.height, 1);
  EXPECT_EQ(s.pixels.size(), 500u);
  // The first frame as printed: 1898165.1 s, the probe at (-300.321, -83.1709, -1481.09).
  EXPECT_DOUBLE_EQ(s.frames[0].timestamp_s, 1898165.1);
  EXPECT_DOUBLE_EQ(s.frames[0].transforms.at("ProbeToTracker").matrix(0, 3), -300.321);
  EXPECT_DOUBLE_EQ(s.frames[0].transforms.at("ProbeToTracker").matrix(2, 3), -1481.09);
  int invalid = 0;
  const std::string text = slurp(path);
  for (size_t at = text.find("TransformStatus = INVALID"); at != std::string::npos;
       at = text.find("TransformStatus = INVALID", at + 1)) {
    ++invalid;
  }
  int read_invalid = 0;
  for (const auto& f : s.frames)
    for (const auto& [name, t] : f.transforms) read_invalid += !t.valid;
  EXPECT_EQ(read_invalid, invalid);
}

TEST(PlusSequence, VideoSequenceDecompressesItsTwentyFrames) {
  const std::string path = data("SyntheticVideoBuffer20.igs.mha");
  const PlusSequence s = read_plus_sequence(path);
  expect_matches_header(s, path);
  EXPECT_EQ(s.frames.size(), 20u);
  ASSERT_GT(s.width, 0);
  ASSERT_GT(s.height, 0);
  EXPECT_EQ(s.pixels.size(), size_t(s.width) * size_t(s.height) * 20 * size_t(s.bytes_per_pixel()));
  EXPECT_DOUBLE_EQ(s.frames[3].timestamp_s, 2.0);
  EXPECT_EQ(s.transform_names(), std::vector<std::string>{"ToolToTracker"});
  // The frames differ (a moving synthetic pattern): not all bytes alike.
  const size_t frame_bytes = s.pixels.size() / 20;
  EXPECT_FALSE(std::equal(s.pixels.begin(), s.pixels.begin() + long(frame_bytes),
                          s.pixels.begin() + long(frame_bytes)));
}

TEST(PlusSequence, NrrdSequenceReadsItsKeyValuesAndGzipData) {
  const std::string path = data("NrrdSample.igs.nrrd");
  const PlusSequence s = read_plus_sequence(path);
  expect_matches_header(s, path);
  EXPECT_EQ(s.frames.size(), 1u);
  EXPECT_EQ(s.width, 256);
  EXPECT_EQ(s.height, 256);
  EXPECT_EQ(s.element_type, "MET_SHORT");
  EXPECT_EQ(s.pixels.size(), 256u * 256u * 2u);
  EXPECT_EQ(s.frames[0].field("Status"), "OK");
  EXPECT_TRUE(std::isnan(s.frames[0].timestamp_s));
}

TEST(PlusSequence, WrittenSequenceReadsBackFieldForFieldAndPixelForPixel) {
  const test::TemporaryFolder dir;
  for (const char* name : {"TransformInterpolationTest.igs.mha", "SyntheticVideoBuffer20.igs.mha",
                           "NrrdSample.igs.nrrd"}) {
    SCOPED_TRACE(name);
    const PlusSequence a = read_plus_sequence(data(name));
    const std::string out = dir.file(std::string(name) + ".igs.mha");
    write_plus_sequence(out, a);
    const PlusSequence b = read_plus_sequence(out);
    EXPECT_EQ(b.header, a.header);
    EXPECT_EQ(b.width, a.width);
    EXPECT_EQ(b.height, a.height);
    EXPECT_EQ(b.channels, a.channels);
    EXPECT_EQ(b.element_type, a.element_type);
    EXPECT_TRUE(b.pixels == a.pixels);
    ASSERT_EQ(b.frames.size(), a.frames.size());
    for (size_t f = 0; f < a.frames.size(); ++f) {
      EXPECT_EQ(b.frames[f].fields, a.frames[f].fields) << "frame " << f;
      EXPECT_TRUE(b.frames[f].timestamp_s == a.frames[f].timestamp_s ||
                  (std::isnan(a.frames[f].timestamp_s) && std::isnan(b.frames[f].timestamp_s)));
      ASSERT_EQ(b.frames[f].transforms.size(), a.frames[f].transforms.size());
      for (const auto& [n, t] : a.frames[f].transforms) {
        EXPECT_EQ(b.frames[f].transforms.at(n).matrix, t.matrix) << n;
        EXPECT_EQ(b.frames[f].transforms.at(n).valid, t.valid) << n;
      }
    }
    // Written twice, the same bytes.
    write_plus_sequence(out + "2.igs.mha", b);
    EXPECT_EQ(slurp(out + "2.igs.mha"), slurp(out));
  }
}

void expect_refused(const std::string& path, const std::string& what) {
  try {
    read_plus_sequence(path);
    FAIL() << path << " was read";
  } catch (const Error& e) {
    const std::string message = e.what();
    EXPECT_NE(message.find(path), std::string::npos) << message;
    EXPECT_NE(message.find(what), std::string::npos) << message;
  }
}

TEST(PlusSequence, BrokenFilesAreRefusedNamingTheProblem) {
  const test::TemporaryFolder dir;
  const std::string good = slurp(data("TransformInterpolationTest.igs.mha"));
  const auto write = [&](const std::string& name, const std::string& text) {
    std::ofstream(dir.file(name), std::ios::binary) << text;
    return dir.file(name);
  };
  const auto replaced = [&](const std::string& from, const std::string& to) {
    std::string t = good;
    t.replace(t.find(from), from.size(), to);
    return t;
  };
  expect_refused(write("cut.igs.mha", good.substr(0, good.size() - 100)), "compressed image data");
  expect_refused(write("header.igs.mha", good.substr(0, 2000)), "ElementDataFile");
  expect_refused(write("status.igs.mha", replaced("ProbeToTrackerTransformStatus = OK",
                                                  "ProbeToTrackerTransformStatus = MAYBE")),
                 "expected OK or INVALID");
  expect_refused(write("matrix.igs.mha", replaced(" 0 0 0 1 \nSeq_Frame0000_ProbeToTrackerTransformStatus",
                                                  " 0 0 0 \nSeq_Frame0000_ProbeToTrackerTransformStatus")),
                 "not 16 numbers");
  expect_refused(write("beyond.igs.mha", replaced("Seq_Frame0000_FrameNumber", "Seq_Frame0900_FrameNumber")),
                 "beyond the 500 frames");
  expect_refused(write("external.igs.mha", replaced("ElementDataFile = LOCAL", "ElementDataFile = x.raw")),
                 "another file");
  expect_refused(write("binary.igs.mha", std::string("\x89PNG\r\n\x1a\n", 8) + good), "binary bytes");
  expect_refused(dir.file("missing.igs.mha"), "cannot open");
}

}  // namespace
}  // namespace crepuscular::recordings
