// OpenIGTLink out, over 127.0.0.1:
// - the reference library's own ReceiveClient example (built unchanged from Debian's
//   openigtlink-examples) receives our TRANSFORMs: the matrices and the timestamps we sent;
// - a client of our own (the library's parser, CRC checked) sees the device names in the order
//   guidance sends them: the on-connect messages, then per frame PatientToCT and NeedleToCT (or
//   a STATUS for a lost marker) and NeedleSafety;
// - a client that never reads is dropped after the send timeout while publishing never waits
//   and a reading client keeps receiving, in order (the latency is benchmarked: bench/RESULTS.md).
#include <gtest/gtest.h>
#include <igtlClientSocket.h>
#include <igtlMessageHeader.h>
#include <igtlStatusMessage.h>
#include <igtlStringMessage.h>
#include <igtlTrackingDataMessage.h>
#include <igtlTransformMessage.h>
#include <sys/socket.h>
#include <netinet/in.h>
#include <arpa/inet.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <thread>

#include <igtl_util.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "igtl/messages.hpp"
#include "igtl/pose_receiver.hpp"
#include "igtl/socket_close.hpp"
#include "igtl/server.hpp"
#include "pipelines/guide_igtl.hpp"
#include "tests/support/network.hpp"
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
  // Publishing only queues: never anywhere near the 300 ms a send to the stalled client waits.
  EXPECT_LT(slowest_ms, 100.0);
  EXPECT_TRUE(wait_until([&] { return server.stats().dropped == 1; }));
  // The reading client got its frames in order to the last; a full queue may have pushed out
  // some when it fell behind (a loaded machine).
  ASSERT_GE(got.size(), 300u);
  for (size_t i = 1; i < got.size(); ++i) {
    ASSERT_LT(std::stoll(got[i - 1].text.substr(60000)), std::stoll(got[i].text.substr(60000)));
  }
  EXPECT_TRUE(got.back().text == big + "599") << "last text of " << got.back().text.size()
                                              << " bytes";
  EXPECT_EQ(server.stats().clients, 1);
}

}  // namespace
}  // namespace crepuscular::igtlink

// --- OpenIGTLink in ------------------------------------------------------------------------------

namespace crepuscular::igtlink {
namespace {

TEST(IgtlPoses, TheLibrarysTrackerServerExampleDrivesOurReceiver) {
  const int port = test::free_loopback_port();
  const test::BackgroundProcess tracker(std::string(CREPUSCULAR_IGTL_TRACKER_SERVER) + " " +
                                        std::to_string(port) + " 100");
  {
    PoseReceiver receiver("igtl://127.0.0.1:" + std::to_string(port));
    // The example sends 100 poses at 100 Hz: (50 cos phi, 50 sin phi, 50 cos phi), phi += 0.2.
    ASSERT_TRUE(wait_until([&] { return receiver.stats().poses >= 40; }));
    const auto p = receiver.latest("Tracker");
    ASSERT_TRUE(p.has_value());
    const Eigen::Vector3d t = p->transform.translation();
    EXPECT_NEAR(t.x(), t.z(), 1e-4);
    EXPECT_NEAR(t.head<2>().norm(), 50.0, 1e-3);
    const Eigen::Matrix3d R = p->transform.linear();
    EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), 1e-4);
    EXPECT_EQ(receiver.stats().dropped, 0);
  }
}

TEST(IgtlPoses, AnUnreachableTrackingServerIsSaidInOurWords) {
  // Nothing listens on a free port: every attempt to connect fails, and is counted and said.
  const int port = test::free_loopback_port();
  std::ostringstream log;
  auto sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(log, true);
  spdlog::default_logger()->sinks().push_back(sink);
  {
    PoseReceiver receiver("igtl://127.0.0.1:" + std::to_string(port));
    ASSERT_TRUE(wait_until([&] { return receiver.stats().failed_connects >= 2; }));
    EXPECT_EQ(receiver.stats().connections, 0);
    EXPECT_EQ(receiver.stats().last_problem, "cannot reach the tracking server");
  }
  spdlog::default_logger()->sinks().pop_back();
  const std::string said = log.str();
  EXPECT_NE(said.find("cannot reach the tracking server at 127.0.0.1:" + std::to_string(port)),
            std::string::npos)
      << said;
  // Said once at first, not once per attempt.
  EXPECT_EQ(said.find("cannot reach", said.find("cannot reach") + 1), std::string::npos) << said;
}

// A hostile or broken sender: our fake tracking server speaks raw bytes.
class FakeTracker {
 public:
  FakeTracker() {
    listener_ = ::socket(AF_INET, SOCK_STREAM, 0);
    int one = 1;
    ::setsockopt(listener_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ::bind(listener_, reinterpret_cast<sockaddr*>(&address), sizeof(address));
    socklen_t length = sizeof(address);
    ::getsockname(listener_, reinterpret_cast<sockaddr*>(&address), &length);
    port_ = ntohs(address.sin_port);
    ::listen(listener_, 4);
  }
  ~FakeTracker() {
    if (client_ >= 0) ::close(client_);
    ::close(listener_);
  }
  int port() const { return port_; }
  void accept() {
    if (client_ >= 0) ::close(client_);
    client_ = ::accept(listener_, nullptr, nullptr);
  }
  void send(const std::string& bytes) {
    ASSERT_EQ(::send(client_, bytes.data(), bytes.size(), MSG_NOSIGNAL), ssize_t(bytes.size()));
  }

 private:
  int listener_ = -1, client_ = -1, port_ = 0;
};

void put_u64(std::string& bytes, size_t at, uint64_t v) {
  for (int i = 0; i < 8; ++i) bytes[at + size_t(i)] = char((v >> (56 - 8 * i)) & 0xff);
}

// igtl-server:PORT: the tracker connects to us; a TRANSFORM and a TDATA message arrive.
TEST(IgtlPoses, InServerModeTheTrackerConnectsAndItsTransformsAndTrackingDataArrive) {
  PoseReceiver receiver("igtl-server:0");
  ASSERT_GT(receiver.port(), 0);
  igtl::ClientSocket::Pointer tracker = connect(receiver.port());
  const Eigen::Isometry3d T = pose(1.1, Eigen::Vector3d(-40, 15, 220));
  const std::string bytes = transform_message("StylusToTracker", T, 42).bytes;
  ASSERT_EQ(tracker->Send(bytes.data(), int(bytes.size())), 1);
  igtl::TrackingDataMessage::Pointer tdata = igtl::TrackingDataMessage::New();
  tdata->SetDeviceName("Tracker");
  igtl::TrackingDataElement::Pointer e = igtl::TrackingDataElement::New();
  e->SetName("ReferenceToTracker");
  igtl::Matrix4x4 m;
  const Eigen::Isometry3d R = pose(-0.2, Eigen::Vector3d(1, 2, 3));
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) m[r][c] = float(R.matrix()(r, c));
  e->SetMatrix(m);
  tdata->AddTrackingDataElement(e);
  tdata->Pack();
  ASSERT_EQ(tracker->Send(tdata->GetPackPointer(), tdata->GetPackSize()), 1);
  ASSERT_TRUE(wait_until([&] { return receiver.latest("ReferenceToTracker").has_value(); }));
  ASSERT_TRUE(receiver.latest("StylusToTracker").has_value());
  EXPECT_LT((receiver.latest("StylusToTracker")->transform.matrix() - T.matrix()).cwiseAbs().maxCoeff(),
            1e-4);
  EXPECT_LT((receiver.latest("ReferenceToTracker")->transform.matrix() - R.matrix())
                .cwiseAbs()
                .maxCoeff(),
            1e-4);
  EXPECT_EQ(receiver.stats().dropped, 0);
}

int open_descriptors() {
  return int(std::distance(std::filesystem::directory_iterator("/proc/self/fd"),
                           std::filesystem::directory_iterator()));
}

// The library's CloseSocket only shuts a connection down; ours also closes the descriptor. 300
// senders that connect, send junk and go leave no descriptor behind (fuzzing found the process
// out of descriptors after 19 000), on the receiving and the serving side alike.
TEST(IgtlPoses, ConnectionsThatComeAndGoLeaveNoDescriptorBehind) {
  PoseReceiver receiver("igtl-server:0");
  Server server(Server::Options{0, 500});
  const int before = open_descriptors();
  for (int i = 0; i < 300; ++i) {
    const int64_t ended = receiver.stats().ended;
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(uint16_t(receiver.port()));
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)), 0);
    const std::string junk(64, 'x');
    ::send(fd, junk.data(), junk.size(), MSG_NOSIGNAL);
    ::close(fd);
    ASSERT_TRUE(wait_until([&] { return receiver.stats().ended > ended; }));
  }
  for (int i = 0; i < 50; ++i) {
    igtl::ClientSocket::Pointer client = connect(server.port());
    ASSERT_TRUE(wait_until([&] { return server.stats().clients == 1; }));
    close_socket(*client);
    server.publish({string_message("NeedleSafety", "x", 0)});  // finds the client gone
    ASSERT_TRUE(wait_until([&] {
      server.publish({string_message("NeedleSafety", "x", 0)});
      return server.stats().clients == 0;
    }));
  }
  EXPECT_LT(open_descriptors() - before, 10);
}

TEST(IgtlPoses, MalformedMessagesDropTheConnectionUnknownTypesAreSkipped) {
  FakeTracker tracker;
  PoseReceiver receiver("igtl://127.0.0.1:" + std::to_string(tracker.port()));
  tracker.accept();
  const Eigen::Isometry3d T = pose(0.7, Eigen::Vector3d(10, 20, 30));
  // An unknown type with a body, then a valid TRANSFORM: the first is skipped, the second read.
  std::string unknown = string_message("Notes", "hello", 0).bytes;
  std::memcpy(&unknown[2], "FOOBAR\0\0\0\0\0\0", 12);
  tracker.send(unknown);
  tracker.send(transform_message("Needle", T, 5).bytes);
  ASSERT_TRUE(wait_until([&] { return receiver.latest("Needle").has_value(); }));
  EXPECT_LT((receiver.latest("Needle")->transform.matrix() - T.matrix()).cwiseAbs().maxCoeff(),
            1e-5);
  EXPECT_EQ(receiver.stats().skipped, 1);

  // Each of these drops the connection (with its reason); the receiver connects again.
  const std::string good = transform_message("Needle", T, 6).bytes;
  std::string bad_crc = good;
  bad_crc[60] ^= 0x40;
  std::string oversized = good.substr(0, 58);
  put_u64(oversized, 42, uint64_t(1) << 30);
  std::string bad_version = good;
  bad_version[0] = 0;
  bad_version[1] = 7;
  const std::vector<std::pair<std::string, std::string>> faults = {
      {bad_crc, "CRC"}, {oversized, "announces"}, {bad_version, "version 7"}};
  int64_t dropped = 0;
  for (const auto& [bytes, reason] : faults) {
    tracker.send(bytes);
    ++dropped;
    ASSERT_TRUE(wait_until([&] { return receiver.stats().dropped == dropped; })) << reason;
    EXPECT_NE(receiver.stats().last_problem.find(reason), std::string::npos)
        << receiver.stats().last_problem;
    tracker.accept();  // the reconnection (after 0.1 s back-off at most)
  }
  // A truncated header, then the sender goes away: a reconnection, no pose from it.
  tracker.send(good.substr(0, 20));
  tracker.accept();
  // The receiver counts a connection once its own connect returns, which may come after the
  // tracker's accept.
  EXPECT_TRUE(wait_until([&] { return receiver.stats().connections >= 5; }));
  // Header version 2 (extended header, no metadata) is read.
  std::string v2 = good.substr(0, 58);
  v2[1] = 2;
  std::string body = std::string("\0\x0c\0\0\0\0\0\0\0\0\0\x01", 12) + good.substr(58);
  put_u64(v2, 42, body.size());
  put_u64(v2, 50, crc64(reinterpret_cast<unsigned char*>(&body[0]), body.size(), crc64(nullptr, 0, 0ULL)));
  const Eigen::Isometry3d T2 = pose(-0.3, Eigen::Vector3d(-5, 6, 7));
  const std::string good2 = transform_message("Needle", T2, 7).bytes;
  body = std::string("\0\x0c\0\0\0\0\0\0\0\0\0\x01", 12) + good2.substr(58);
  v2 = good2.substr(0, 58);
  v2[1] = 2;
  put_u64(v2, 42, body.size());
  put_u64(v2, 50, crc64(reinterpret_cast<unsigned char*>(&body[0]), body.size(), crc64(nullptr, 0, 0ULL)));
  tracker.send(v2 + body);
  ASSERT_TRUE(wait_until([&] {
    const auto p = receiver.latest("Needle");
    return p && (p->transform.matrix() - T2.matrix()).cwiseAbs().maxCoeff() < 1e-5;
  }));
  EXPECT_EQ(receiver.stats().dropped, dropped);
}

}  // namespace
}  // namespace crepuscular::igtlink
