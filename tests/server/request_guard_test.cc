// The browser view's Host and cross-site checks (server/http/request_guard.h, issue 52).
#include "server/http/request_guard.h"

#include <gtest/gtest.h>

namespace lifemap::server {
namespace {

TEST(RequestGuard, HostMustNameThisServer) {
  const HostPolicy policy = MakeHostPolicy("127.0.0.1", {"view.lab.example", ".robots.example"});
  for (const char* ok :
       {"", "127.0.0.1:8080", "[::1]:8080", "10.1.2.3", "localhost", "LocalHost:80",
        "app.localhost", "view.lab.example.", "robots.example", "a.b.robots.example:443"}) {
    EXPECT_TRUE(CheckHost(ok, policy).ok()) << ok;
  }
  for (const char* refused : {"attacker.example", "view.lab.example.attacker.example",
                              "localhost.attacker.example", "xrobots.example", "[::1"}) {
    const absl::Status s = CheckHost(refused, policy);
    EXPECT_TRUE(absl::IsPermissionDenied(s)) << refused;
  }
  // Control characters in a forged Host do not reach the message raw.
  const absl::Status s = CheckHost("evil\x1b[2J\nexample", policy);
  EXPECT_EQ(s.message().find('\x1b'), absl::string_view::npos) << s;
  EXPECT_EQ(s.message().find('\n'), absl::string_view::npos) << s;
  EXPECT_TRUE(CheckHost("anything.example", MakeHostPolicy("127.0.0.1", {"*"})).ok());
  EXPECT_TRUE(CheckHost("lifemap-box:8080", MakeHostPolicy("lifemap-box", {})).ok());
}

TEST(RequestGuard, ChangesComeFromTheViewsOwnPagesAsJson) {
  const char* host = "127.0.0.1:8080";
  const char* json = "application/json";
  EXPECT_TRUE(CheckStateChange("GET", host, "https://a.example", "cross-site", "", false).ok());
  EXPECT_TRUE(CheckStateChange("POST", host, "", "", json, true).ok()) << "curl";
  EXPECT_TRUE(
      CheckStateChange("POST", host, "http://127.0.0.1:8080", "same-origin", json, true).ok());
  EXPECT_TRUE(CheckStateChange("DELETE", host, "", "none", "", false).ok()) << "typed URL";
  EXPECT_TRUE(CheckStateChange("POST", host, "", "", "Application/JSON; charset=utf-8", true).ok());
  EXPECT_TRUE(absl::IsPermissionDenied(
      CheckStateChange("POST", host, "http://127.0.0.1:8080", "cross-site", json, true)));
  EXPECT_TRUE(
      absl::IsPermissionDenied(CheckStateChange("POST", host, "", "same-site", json, true)));
  EXPECT_TRUE(absl::IsPermissionDenied(
      CheckStateChange("DELETE", host, "http://127.0.0.1:9090", "", "", false)));
  EXPECT_TRUE(absl::IsPermissionDenied(CheckStateChange("POST", host, "null", "", json, true)));
  EXPECT_TRUE(absl::IsInvalidArgument(CheckStateChange("POST", host, "", "", "text/plain", true)));
  EXPECT_TRUE(absl::IsInvalidArgument(
      CheckStateChange("POST", host, "", "", "application/x-www-form-urlencoded", true)));
  EXPECT_TRUE(absl::IsInvalidArgument(CheckStateChange("POST", host, "", "", "", true)));
}

}  // namespace
}  // namespace lifemap::server
