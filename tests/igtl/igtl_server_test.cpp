// OpenIGTLink out, over 127.0.0.1:
// - the reference library's own ReceiveClient example (built unchanged from Debian's
//   openigtlink-examples) receives our TRANSFORMs: the matrices and the timestamps we sent;
// - a client of our own (the library's parser, CRC checked) sees the device names in the order
//   guidance sends them: the on-connect messages, then per frame PatientToCT and NeedleToCT (or
//   a STATUS for a lost marker) and NeedleSafety;
// - a client that never reads is dropped after the send timeout while publishing never waits
//   and a reading client keeps receiving every frame; the publish-to-socket latency is measured.
#include <gtest/gtest.h>
#include <igtlClientSocket.h>
#include <igtlMessageHeader.h>
#include <igtlStatusMessage.h>
#include <igtlStringMessage.h>
#include <igtlTransformMessage.h>
#include <sys/socket.h>
#include <netinet/in.h>
#include <arpa/inet.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <regex>
#include <sstream>
#include <thread>

#include "igtl/messages.hpp"
#include "igtl/server.hpp"
#include "pipelines/guide_igtl.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::igtlink {
namespace {

using Clock = std::chrono::steady_clock;

template <typename F>
bool wait_until(F done, double seconds = 10.0) {
  const auto end = Clock::now() + std::chrono::duration<double>(seconds);
  while (Clock::now() < end) {
    if (done()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return done();
}

Eigen::Isometry3d pose(double angle, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(angle, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  T.translation() = t;
  return T;
}

// What our own client read: device type, name, timestamp, and the transform or text.
struct Received {
  std::string type, name;
  uint32_t sec = 0, nanosec = 0;
  Eigen::Matrix4d matrix = Eigen::Matrix4d::Zero();
  std::string text;
  int status = -1;
  bool crc_ok = false;
};

// Reads messages until `count` arrived or the server closes; the library parses, CRC checked.
// Also stops after a message whose text is `last` (when given).
std::vector<Received> read_messages(igtl::ClientSocket::Pointer socket, size_t count,
                                    const std::string& last = "") {
  std::vector<Received> out;
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  while (out.size() < count && (last.empty() || out.empty() || out.back().text != last)) {
    header->InitPack();
    if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) !=
        header->GetPackSize()) {
      break;
    }
    header->Unpack();
    Received r;
    r.type = header->GetDeviceType();
    r.name = header->GetDeviceName();
    igtl::TimeStamp::Pointer ts = igtl::TimeStamp::New();
    header->GetTimeStamp(ts);
    ts->GetTimeStamp(&r.sec, &r.nanosec);
    if (r.type == "TRANSFORM") {
      igtl::TransformMessage::Pointer m = igtl::TransformMessage::New();
      m->SetMessageHeader(header);
      m->AllocatePack();
      socket->Receive(m->GetPackBodyPointer(), m->GetPackBodySize());
      r.crc_ok = (m->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) != 0;
      igtl::Matrix4x4 matrix;
      m->GetMatrix(matrix);
      for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) r.matrix(i, j) = matrix[i][j];
    } else if (r.type == "STRING") {
      igtl::StringMessage::Pointer m = igtl::StringMessage::New();
      m->SetMessageHeader(header);
      m->AllocatePack();
      socket->Receive(m->GetPackBodyPointer(), m->GetPackBodySize());
      r.crc_ok = (m->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) != 0;
      r.text = m->GetString();
    } else if (r.type == "STATUS") {
      igtl::StatusMessage::Pointer m = igtl::StatusMessage::New();
      m->SetMessageHeader(header);
      m->AllocatePack();
      socket->Receive(m->GetPackBodyPointer(), m->GetPackBodySize());
      r.crc_ok = (m->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) != 0;
      r.status = m->GetCode();
      r.text = m->GetStatusString();
    } else {
      socket->Skip(int(header->GetBodySizeToRead()), 1);
      r.crc_ok = true;
    }
    out.push_back(r);
  }
  return out;
}

igtl::ClientSocket::Pointer connect(int port) {
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  EXPECT_EQ(socket->ConnectToServer("127.0.0.1", port), 0);
  return socket;
}

TEST(IgtlServer, TheLibrarysReceiveClientExampleGetsOurMatricesAndTimestamps) {
  const test::TemporaryFolder dir;
  const std::string log = (dir / "client.log").string(), out = (dir / "client.out").string();
  std::vector<Eigen::Isometry3d> sent;
  std::vector<int64_t> stamps;
  int port = 0;
  {
    Server server(Server::Options{0, 500});
    port = server.port();
    ASSERT_GT(port, 0);
    const std::string command = std::string(CREPUSCULAR_IGTL_RECEIVE_CLIENT) + " 127.0.0.1 " +
                                std::to_string(port) + " > " + out + " 2> " + log + " &";
    ASSERT_EQ(std::system(command.c_str()), 0);
    ASSERT_TRUE(wait_until([&] { return server.stats().clients == 1; }));
    for (int i = 0; i < 5; ++i) {
      sent.push_back(pose(0.3 * i, Eigen::Vector3d(10.5 * i, -20.25, 300 + i)));
      stamps.push_back(int64_t(1700000000) * 1000000000 + i * 33333333);
      server.publish({transform_message("NeedleToCT", sent.back(), stamps.back())});
    }
    ASSERT_TRUE(wait_until([&] { return server.stats().messages_sent == 5; }));
  }  // the server closes; the example sees the end of the stream and exits
  ASSERT_TRUE(wait_until([&] {
    std::ifstream in(out);
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    return std::count(text.begin(), text.end(), '=') >= 5 * 13;
  }));
  std::ifstream in(out);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  // PrintMatrix: a line of '=' then four rows of four numbers.
  const std::regex number(R"([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)");
  std::vector<double> values;
  for (std::sregex_iterator it(text.begin(), text.end(), number), end; it != end; ++it) {
    values.push_back(std::stod(it->str()));
  }
  ASSERT_EQ(values.size(), 5u * 16u) << text;
  for (size_t m = 0; m < 5; ++m) {
    for (int r = 0; r < 4; ++r)
      for (int c = 0; c < 4; ++c) {
        EXPECT_NEAR(values[m * 16 + size_t(r * 4 + c)], sent[m].matrix()(r, c), 1e-4)
            << "matrix " << m << " (" << r << ", " << c << ")";
      }
  }
  std::ifstream err_in(log);
  std::string err((std::istreambuf_iterator<char>(err_in)), std::istreambuf_iterator<char>());
  const std::regex stamp(R"(Time stamp: ([0-9]+)\.([0-9]{9}))");
  std::vector<int64_t> got;
  for (std::sregex_iterator it(err.begin(), err.end(), stamp), end; it != end; ++it) {
    got.push_back(std::stoll((*it)[1]) * 1000000000 + std::stoll((*it)[2]));
  }
  ASSERT_EQ(got.size(), 5u) << err;
  for (size_t i = 0; i < 5; ++i) {
    // The header's timestamp is a 32.32 fixed-point number: within a nanosecond or two.
    EXPECT_NEAR(double(got[i]), double(stamps[i]), 2.0) << i;
  }
  EXPECT_NE(err.find("Receiving TRANSFORM data type."), std::string::npos) << err;
}

// Guidance's messages, frame by frame, as a client sees them.
TEST(IgtlServer, GuidanceSendsOnConnectMessagesThenPosesAndSafetyPerFrame) {
  planning::PlanData plan;
  plan.dir = "(no folder)";
  plan.tumor_centre = Eigen::Vector3d(5, -7, 12);
  overlay::GuidanceSetup setup;
  setup.T_ct_patient = pose(0.2, Eigen::Vector3d(1, 2, 3));
  setup.tip_in_needle = Eigen::Vector3d(0, 0, 150);
  pipelines::GuidanceBroadcast broadcast(Server::Options{0, 500}, plan, setup);
  igtl::ClientSocket::Pointer client = connect(broadcast.server().port());
  ASSERT_TRUE(wait_until([&] { return broadcast.server().stats().clients == 1; }));

  tracking::TrackResult both, needle_lost;
  tracking::BoardStatus patient, needle;
  patient.board = "patient";
  patient.tracked = true;
  patient.T_cam_board = pose(0.5, Eigen::Vector3d(100, 0, 500));
  needle.board = "needle";
  needle.tracked = true;
  needle.T_cam_board = pose(-0.4, Eigen::Vector3d(-50, 20, 400));
  both.boards = {patient, needle};
  needle.tracked = false;
  needle_lost.boards = {patient, needle};
  tracking::Frame frame;
  frame.timestamp_ns = 123456789012;
  broadcast.poses(frame, both);
  overlay::GuidanceFrameInfo info;
  info.timestamp_ns = frame.timestamp_ns;
  broadcast.safety(info);
  frame.timestamp_ns += 33333333;
  broadcast.poses(frame, needle_lost);

  const std::vector<Received> got = read_messages(client, 7);
  ASSERT_EQ(got.size(), 7u);
  const std::vector<std::pair<std::string, std::string>> expected = {
      {"TRANSFORM", "NeedleTipToNeedle"}, {"POINT", "Target"},       {"TRANSFORM", "PatientToCT"},
      {"TRANSFORM", "NeedleToCT"},        {"STRING", "NeedleSafety"}, {"TRANSFORM", "PatientToCT"},
      {"STATUS", "NeedleToCT"}};
  for (size_t i = 0; i < expected.size(); ++i) {
    EXPECT_EQ(got[i].type, expected[i].first) << i;
    EXPECT_EQ(got[i].name, expected[i].second) << i;
    EXPECT_TRUE(got[i].crc_ok) << i;
  }
  EXPECT_NEAR(got[0].matrix(2, 3), 150.0, 1e-4);
  const Eigen::Matrix4d T_ct_needle = (setup.T_ct_patient * patient.T_cam_board.inverse() *
                                       both.boards[1].T_cam_board)
                                          .matrix();
  EXPECT_LT((got[3].matrix - T_ct_needle).cwiseAbs().maxCoeff(), 1e-3);
  EXPECT_LT((got[2].matrix - setup.T_ct_patient.matrix()).cwiseAbs().maxCoeff(), 1e-5);
  // The header's 32.32 fixed-point timestamp: within a few nanoseconds.
  EXPECT_NEAR(double(int64_t(got[3].sec) * 1000000000 + got[3].nanosec), 123456789012.0, 10.0);
  EXPECT_EQ(got[4].text, "no needle reading");
  EXPECT_EQ(got[6].status, kStatusNotFound);
  EXPECT_EQ(got[6].text, "needle marker lost");
}

TEST(IgtlServer, AClientThatNeverReadsIsDroppedAndNeverSlowsPublishing) {
  Server server(Server::Options{0, 300});
  // A raw TCP client that connects and never reads a byte.
  const int stalled = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(uint16_t(server.port()));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::connect(stalled, reinterpret_cast<sockaddr*>(&address), sizeof(address)), 0);
  igtl::ClientSocket::Pointer reader = connect(server.port());
  ASSERT_TRUE(wait_until([&] { return server.stats().clients == 2; }));
  std::vector<Received> got;
  const std::string big(60000, 'x');  // a STRING holds at most 65535 bytes
  std::thread reading([&] { got = read_messages(reader, 600, big + "599"); });

  // 600 frames of 60 kB at about 300 Hz: far more than the stalled client's socket buffers.
  double slowest_ms = 0;
  for (int i = 0; i < 600; ++i) {
    const Message m = string_message("NeedleSafety", big + std::to_string(i), i);
    const auto t0 = Clock::now();
    server.publish({m});
    slowest_ms =
        std::max(slowest_ms, std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    std::this_thread::sleep_for(std::chrono::microseconds(3000));
  }
  reading.join();
  ::close(stalled);
  EXPECT_LT(slowest_ms, 5.0);  // publish only queues
  EXPECT_TRUE(wait_until([&] { return server.stats().dropped == 1; }));
  // The reading client got its frames in order; a full queue may have pushed out a few.
  ASSERT_GE(got.size(), 590u);
  EXPECT_TRUE(got.back().text == big + "599") << "last text of " << got.back().text.size()
                                              << " bytes";
  const Server::Stats s = server.stats();
  EXPECT_EQ(s.clients, 1);
  EXPECT_LE(s.latency_median_ms, 1.0) << "publish to socket, median";
}

}  // namespace
}  // namespace crepuscular::igtlink
