#include "tests/testing/test_util.h"

#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <vector>

#include <opencv2/imgcodecs.hpp>

namespace lifemap::testing {

namespace fs = std::filesystem;

std::string SharedDataDir() {
  if (const char* env = std::getenv("LIFEMAP_DATA"); env && *env) {
    return fs::is_directory(env) ? std::string(env) : std::string();
  }
  const fs::path dir = fs::path(LIFEMAP_SOURCE_DIR) / ".." / "shared" / "data";
  return fs::is_directory(dir) ? fs::canonical(dir).string() : std::string();
}

std::string SharedDataset(const std::string& name) {
  const std::string root = SharedDataDir();
  if (root.empty()) return "";
  const fs::path dir = fs::path(root) / name;
  return fs::is_directory(dir) ? dir.string() : std::string();
}

TempDir::TempDir() {
  std::string pattern = (fs::temp_directory_path() / "lifemap-test-XXXXXX").string();
  std::vector<char> buf(pattern.begin(), pattern.end());
  buf.push_back('\0');
  if (mkdtemp(buf.data()) == nullptr) std::abort();
  path_ = buf.data();
}

TempDir::~TempDir() {
  std::error_code ec;
  fs::remove_all(path_, ec);
}

std::string PngBytes(const cv::Mat& image) {
  std::vector<unsigned char> buf;
  cv::imencode(".png", image, buf);
  return std::string(buf.begin(), buf.end());
}

std::string JpegBytes(const cv::Mat& image) {
  std::vector<unsigned char> buf;
  cv::imencode(".jpg", image, buf, {cv::IMWRITE_JPEG_QUALITY, 90});
  return std::string(buf.begin(), buf.end());
}

v1::Frame MakeFrame(int width, int height, double depth_m, double timestamp_s, uint64_t sequence) {
  cv::Mat depth(height, width, CV_16UC1, cv::Scalar(static_cast<int>(depth_m * 5000)));
  cv::Mat color(height, width, CV_8UC3);
  for (int r = 0; r < height; ++r) {
    for (int c = 0; c < width; ++c) {
      const bool dark = ((r / 16) + (c / 16)) % 2 == 0;
      color.at<cv::Vec3b>(r, c) = dark ? cv::Vec3b(40, 60, 80) : cv::Vec3b(200, 210, 220);
    }
  }
  v1::Frame f;
  f.set_sequence(sequence);
  f.set_timestamp_s(timestamp_s);
  auto* k = f.mutable_intrinsics();
  k->set_fx(525.0 * width / 640.0);
  k->set_fy(525.0 * height / 480.0);
  k->set_cx((width - 1) / 2.0);
  k->set_cy((height - 1) / 2.0);
  k->set_width(static_cast<uint32_t>(width));
  k->set_height(static_cast<uint32_t>(height));
  auto* d = f.mutable_depth();
  d->set_encoding(v1::DEPTH_PNG16);
  d->set_data(PngBytes(depth));
  d->set_depth_scale(5000.0);
  auto* c = f.mutable_color();
  c->set_encoding(v1::COLOR_JPEG);
  c->set_data(JpegBytes(color));
  return f;
}

void WriteSyntheticTum(const std::string& dir, int frames, double step_m, int width, int height) {
  fs::create_directories(fs::path(dir) / "rgb");
  fs::create_directories(fs::path(dir) / "depth");
  std::ofstream rgb_list(fs::path(dir) / "rgb.txt");
  std::ofstream depth_list(fs::path(dir) / "depth.txt");
  std::ofstream gt(fs::path(dir) / "groundtruth.txt");
  std::ofstream(fs::path(dir) / "intrinsics.txt")
      << 525.0 * width / 640.0 << " " << 525.0 * height / 480.0 << " " << (width - 1) / 2.0 << " "
      << (height - 1) / 2.0 << "\n";
  rgb_list << "# color images\n";
  depth_list << "# depth maps\n";
  gt << "# timestamp tx ty tz qx qy qz qw\n";
  char name[64];
  for (int i = 0; i < frames; ++i) {
    const double t = 1700000000.0 + i / 30.0;
    const v1::Frame f = MakeFrame(width, height, 1.0 + 0.01 * i, t, static_cast<uint64_t>(i));
    std::snprintf(name, sizeof(name), "%.6f.png", t);
    std::ofstream(fs::path(dir) / "rgb" / name, std::ios::binary) << PngBytes(
        cv::imdecode(std::vector<unsigned char>(f.color().data().begin(), f.color().data().end()),
                     cv::IMREAD_COLOR));
    std::ofstream(fs::path(dir) / "depth" / name, std::ios::binary) << f.depth().data();
    const std::string stamp(name, std::strlen(name) - 4);  // without ".png"
    rgb_list << stamp << " rgb/" << name << "\n";
    depth_list << stamp << " depth/" << name << "\n";
  }
  // Ground truth at 100 Hz over the whole span.
  for (int j = 0; j <= frames * 100 / 30 + 1; ++j) {
    const double t = 1700000000.0 + j / 100.0;
    char line[128];
    std::snprintf(line, sizeof(line), "%.4f %.6f 0 0 0 0 0 1\n", t, step_m * 30.0 * (j / 100.0));
    gt << line;
  }
}

bool MakeTestCertificates(const std::string& dir) {
  // P-256 keys: quick to make; valid for two days.
  const std::string key = "-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes";
  std::ofstream(dir + "/server.ext") << "subjectAltName=DNS:localhost,IP:127.0.0.1\n";
  std::ofstream(dir + "/client.ext") << "extendedKeyUsage=clientAuth\n";
  const std::vector<std::string> commands = {
      "openssl req -x509 " + key + " -keyout ca.key -out ca.pem -days 2 -subj /CN=lifemap-test-ca",
      "openssl req -x509 " + key +
          " -keyout other-ca.key -out other-ca.pem -days 2 -subj /CN=another-ca",
      "openssl req " + key + " -keyout server.key -out server.csr -subj /CN=localhost",
      "openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out "
      "server.pem -days 2 -extfile server.ext",
      "openssl req " + key + " -keyout client.key -out client.csr -subj /CN=robot-1",
      "openssl x509 -req -in client.csr -CA ca.pem -CAkey ca.key -CAcreateserial -out "
      "client.pem -days 2 -extfile client.ext",
  };
  for (const auto& c : commands) {
    const std::string line = "cd '" + dir + "' && " + c + " > openssl.log 2>&1";
    if (std::system(line.c_str()) != 0) {
      std::ifstream log(dir + "/openssl.log");
      std::cerr << "openssl failed: " << c << "\n" << log.rdbuf() << "\n";
      return false;
    }
  }
  return true;
}

}  // namespace lifemap::testing
