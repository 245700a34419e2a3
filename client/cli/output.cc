#include "client/cli/output.h"

#include <algorithm>
#include <ctime>
#include <iostream>

#include <google/protobuf/util/json_util.h>
#include <nlohmann/json.hpp>

#include "absl/strings/str_format.h"
#include "core/common/utf8.h"

namespace lifemap::cli {

std::string ToJson(const google::protobuf::Message& message, bool multiline) {
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = multiline;
  options.always_print_primitive_fields = true;
  options.preserve_proto_field_names = true;
  std::string out;
  (void)google::protobuf::util::MessageToJsonString(message, &out, options);
  return out;
}

namespace {
bool json_errors = false;

void PrintError(absl::StatusCode code, absl::string_view message) {
  std::cerr << "lifemap: " << EscapeForLog(message) << " [" << absl::StatusCodeToString(code)
            << "]\n";
  if (json_errors) {
    const nlohmann::json error = {
        {"error", {{"code", absl::StatusCodeToString(code)}, {"message", std::string(message)}}}};
    std::cout << error.dump() << std::endl;
  }
}
}  // namespace

void SetJsonErrors(bool json) { json_errors = json; }

int Fail(const absl::Status& status) {
  PrintError(status.code(), status.message());
  return 1;
}

int UsageError(const std::string& message) {
  PrintError(absl::StatusCode::kInvalidArgument, message);
  return 2;
}

std::string Shown(const std::string& text, const char* empty) {
  return text.empty() ? std::string(empty) : EscapeForLog(text);
}

std::string HumanBytes(uint64_t bytes) {
  const char* units[] = {"B", "KB", "MB", "GB", "TB"};
  double v = static_cast<double>(bytes);
  int u = 0;
  while (v >= 1000.0 && u < 4) {
    v /= 1000.0;
    ++u;
  }
  return u == 0 ? absl::StrFormat("%d B", bytes) : absl::StrFormat("%.1f %s", v, units[u]);
}

std::string HumanTime(double seconds_since_epoch) {
  if (seconds_since_epoch <= 0) return "-";
  const std::time_t t = static_cast<std::time_t>(seconds_since_epoch);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof(buf), "%Y-%m-%d %H:%M:%S UTC", &tm);
  return buf;
}

double Percentile(std::vector<double> values, double percent) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const size_t i =
      std::min(values.size() - 1, static_cast<size_t>(percent / 100.0 * (values.size() - 1) + 0.5));
  return values[i];
}

}  // namespace lifemap::cli
