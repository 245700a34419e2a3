// The browser view against hostile pages and clients (issue 52, items 8-10): DNS rebinding and
// cross-site requests are refused, slow clients do not stop it (nor gRPC), and its errors name
// no map the caller may not see. A real lifemapd with `--http` on loopback, no keys required.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_replace.h"
#include "server/server.h"
#include "tests/integration/server_fixture.h"

// Last: it includes <resolv.h>, whose `_res` macro breaks Eigen's headers included after it.
#include <httplib.h>

namespace lifemap {
namespace {

class WebTest : public testing::ServerTest {
 protected:
  void SetUp() override {
    server::ServerConfig config;
    config.http_listen = "127.0.0.1:0";
    config.http_allowed_hosts = {"lifemap.lab.example"};
    StartServer(config);
    ASSERT_GT(server_->http_port(), 0);
    ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  }

  httplib::Client Http() {
    httplib::Client c("127.0.0.1", server_->http_port());
    c.set_connection_timeout(5);
    c.set_read_timeout(10);
    return c;
  }

  // A connection that sends the start of a request and then nothing (a slow client): -1 when
  // it could not connect.
  int SlowConnection() {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(server_->http_port()));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
      close(fd);
      return -1;
    }
    const char start[] = "GET /api/maps HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ";
    if (send(fd, start, sizeof(start) - 1, MSG_NOSIGNAL) < 0) {
      close(fd);
      return -1;
    }
    return fd;
  }

  const std::string kAnnotation = R"({"class": "chair", "boxes": [[0, 0, 0, 0.5, 0.5, 0.5]]})";
};

// Item 8: a page whose name an attacker points at 127.0.0.1 (DNS rebinding) sends its own Host.
TEST_F(WebTest, ARequestForAnotherNameIsRefusedWhateverItAsks) {
  auto http = Http();
  for (const char* path : {"/api/maps", "/api/maps/lab/training.tar", "/", "/api/session"}) {
    auto refused = http.Get(path, {{"Host", "attacker.example:8080"}});
    ASSERT_TRUE(refused) << path;
    EXPECT_EQ(refused->status, 403) << path << ": " << refused->body;
    EXPECT_NE(refused->body.find("does not answer to the name"), std::string::npos)
        << refused->body;
    EXPECT_EQ(refused->body.find("\"lab\""), std::string::npos) << "no map is told";
  }
  // Its own names: the address, localhost, a configured name and domains of it.
  for (const char* host : {"127.0.0.1", "localhost:1234", "LIFEMAP.lab.example", "[::1]:80"}) {
    auto ok = http.Get("/api/maps", {{"Host", host}});
    ASSERT_TRUE(ok) << host;
    EXPECT_EQ(ok->status, 200) << host << ": " << ok->body;
  }
  auto sub = http.Get("/api/maps", {{"Host", "view.lifemap.lab.example"}});
  ASSERT_TRUE(sub);
  EXPECT_EQ(sub->status, 403) << "a name, not a domain, was configured";
}

// Item 8: a page of any origin could POST an annotation as text/plain (no CORS preflight).
TEST_F(WebTest, AChangeFromAnotherSitesPageIsRefusedAndTheViewsOwnIsStored) {
  auto http = Http();
  const std::string own = "http://127.0.0.1:" + std::to_string(server_->http_port());
  auto plain = http.Post("/api/maps/lab/annotations", kAnnotation, "text/plain");
  ASSERT_TRUE(plain);
  EXPECT_EQ(plain->status, 415) << plain->body;
  EXPECT_NE(plain->body.find("must be JSON"), std::string::npos) << plain->body;
  auto foreign = http.Post("/api/maps/lab/annotations", {{"Origin", "https://attacker.example"}},
                           kAnnotation, "application/json");
  ASSERT_TRUE(foreign);
  EXPECT_EQ(foreign->status, 403) << foreign->body;
  auto cross = http.Post("/api/maps/lab/annotations", {{"Sec-Fetch-Site", "cross-site"}},
                         kAnnotation, "application/json");
  ASSERT_TRUE(cross);
  EXPECT_EQ(cross->status, 403) << cross->body;
  EXPECT_NE(cross->body.find("another site's page"), std::string::npos) << cross->body;
  auto deleted = http.Delete("/api/maps/lab/annotations/1", {{"Origin", "null"}});
  ASSERT_TRUE(deleted);
  EXPECT_EQ(deleted->status, 403) << deleted->body;
  auto listed = http.Get("/api/maps/lab/annotations");
  ASSERT_TRUE(listed);
  EXPECT_EQ(listed->body.find("chair"), std::string::npos) << "nothing refused was stored";

  // The view's own page: same origin, JSON.
  auto stored =
      http.Post("/api/maps/lab/annotations", {{"Origin", own}, {"Sec-Fetch-Site", "same-origin"}},
                kAnnotation, "application/json; charset=utf-8");
  ASSERT_TRUE(stored);
  EXPECT_EQ(stored->status, 201) << stored->body;
  // A client that is not a browser (no Origin, no Sec-Fetch-Site), as curl: JSON is enough.
  auto curl = http.Post("/api/maps/lab/annotations", kAnnotation, "application/json");
  ASSERT_TRUE(curl);
  EXPECT_EQ(curl->status, 201) << curl->body;
}

// Item 9: 200 slow connections (a request's start, then nothing) took every thread of the view.
TEST_F(WebTest, SlowClientsStopNeitherTheViewNorGrpcAndAStopDoesNotWaitForThem) {
  std::vector<int> slow;
  for (int i = 0; i < 200; ++i) {
    const int fd = SlowConnection();
    if (fd >= 0) slow.push_back(fd);
  }
  ASSERT_GE(slow.size(), 150u);
  const auto asked = std::chrono::steady_clock::now();
  auto http = Http();
  auto maps = http.Get("/api/maps");
  ASSERT_TRUE(maps) << "the view did not answer beside 200 slow connections";
  EXPECT_EQ(maps->status, 200);
  EXPECT_LT(std::chrono::steady_clock::now() - asked, std::chrono::seconds(4));
  EXPECT_TRUE(client_->ListMaps().ok()) << "gRPC keeps serving";
  // Most slow connections are cut within a few seconds (one client's beyond 32).
  std::this_thread::sleep_for(std::chrono::seconds(3));
  size_t open = 0;
  for (int fd : slow) {
    char byte = 0;
    const ssize_t n = recv(fd, &byte, 1, MSG_DONTWAIT);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) ++open;
  }
  EXPECT_LE(open, 40u) << "one client keeps at most 32 connections";
  const auto stopping = std::chrono::steady_clock::now();
  server_.reset();
  EXPECT_LT(std::chrono::steady_clock::now() - stopping, std::chrono::seconds(8))
      << "a stop does not wait for slow clients";
  for (int fd : slow) close(fd);
}

// Item 10: comparing a map's visit with another map's named that map ("it is of map 'hall'").
TEST_F(WebTest, ChangesNameNoOtherMap) {
  ASSERT_TRUE(client_->CreateMap("hall", "").ok());
  v1::StartVisitRequest visit;
  visit.set_map("lab");
  auto lab_visit = client_->StartVisit(visit);
  visit.set_map("hall");
  auto hall_visit = client_->StartVisit(visit);
  ASSERT_TRUE(lab_visit.ok() && hall_visit.ok());
  const auto grpc = client_->GetChanges("lab", lab_visit->id(), hall_visit->id()).status();
  EXPECT_TRUE(absl::IsNotFound(grpc)) << grpc;
  EXPECT_EQ(grpc.message().find("hall"), std::string::npos) << grpc;
  const auto none = client_->GetChanges("lab", lab_visit->id(), 9999).status();
  EXPECT_EQ(none.message(),
            absl::StrReplaceAll(grpc.message(), {{std::to_string(hall_visit->id()), "9999"}}))
      << "another map's visit and no visit at all read the same";
  auto http = Http();
  auto view = http.Get("/api/maps/lab/changes?from=" + std::to_string(lab_visit->id()) +
                       "&to=" + std::to_string(hall_visit->id()));
  ASSERT_TRUE(view);
  EXPECT_EQ(view->status, 404) << view->body;
  EXPECT_EQ(view->body.find("hall"), std::string::npos) << view->body;
}

}  // namespace
}  // namespace lifemap
