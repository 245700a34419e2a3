// TLS and mTLS (issue 17): certificates made by openssl at run time; a client with the right
// CA talks to the server, one talking plaintext or trusting another CA gets a clear error.
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

class TlsTest : public testing::ServerTest {
 protected:
  void SetUp() override {
    ASSERT_TRUE(testing::MakeTestCertificates(tmp_.path())) << "openssl (Debian's) is needed";
  }
  void StartTls(bool require_client_certificate) {
    server::ServerConfig config;
    config.tls_cert = tmp_.File("server.pem");
    config.tls_key = tmp_.File("server.key");
    if (require_client_certificate) config.tls_client_ca = tmp_.File("ca.pem");
    config.listen = "127.0.0.1:0";
    config.db_path = tmp_.File("lifemap.db");
    config.shutdown_grace_s = 2;
    auto s = server::LifemapServer::Start(config);
    ASSERT_TRUE(s.ok()) << s.status();
    server_ = *std::move(s);
    target_ = "127.0.0.1:" + std::to_string(server_->port());
  }
  client::ClientOptions Options() {
    auto options = client::ClientOptions::At(target_);
    options.connect_timeout_s = 2;
    return options;
  }
};

TEST_F(TlsTest, AClientTrustingTheServersCaIsServedAndOthersAreToldWhy) {
  StartTls(false);
  auto options = Options();
  options.tls_ca_file = tmp_.File("ca.pem");
  auto c = client::Client::Connect(options);
  ASSERT_TRUE(c.ok()) << c.status();
  ASSERT_TRUE((*c)->CreateMap("lab", "").ok());
  auto info = (*c)->GetServerInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_TRUE(info->tls());

  const auto plaintext = client::Client::Connect(Options()).status();
  EXPECT_TRUE(absl::IsUnavailable(plaintext)) << plaintext;
  EXPECT_NE(plaintext.message().find("if the server speaks TLS, connect with --tls-ca"),
            std::string::npos)
      << plaintext;
  options.tls_ca_file = tmp_.File("other-ca.pem");
  const auto wrong_ca = client::Client::Connect(options).status();
  EXPECT_TRUE(absl::IsUnavailable(wrong_ca)) << wrong_ca;
  EXPECT_NE(wrong_ca.message().find("signed by the CA given (--tls-ca)"), std::string::npos)
      << wrong_ca;
}

TEST_F(TlsTest, WithClientCertificatesRequiredOnlyClientsWithOneAreServed) {
  StartTls(true);
  auto options = Options();
  options.tls_ca_file = tmp_.File("ca.pem");
  EXPECT_FALSE(client::Client::Connect(options).ok());  // no client certificate
  options.tls_cert_file = tmp_.File("client.pem");
  EXPECT_TRUE(absl::IsInvalidArgument(client::Client::Connect(options).status()));  // no key
  options.tls_key_file = tmp_.File("client.key");
  auto c = client::Client::Connect(options);
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_TRUE((*c)->ListMaps().ok());
}

TEST_F(TlsTest, AServerWithAnUnreadableCertificateDoesNotStart) {
  server::ServerConfig config;
  config.db_path = tmp_.File("lifemap.db");
  config.listen = "127.0.0.1:0";
  config.tls_cert = tmp_.File("missing.pem");
  config.tls_key = tmp_.File("server.key");
  auto s = server::LifemapServer::Start(config);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.status().message().find("missing.pem"), std::string::npos) << s.status();
  config.tls_cert = tmp_.File("server.ext");  // not PEM
  s = server::LifemapServer::Start(config);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.status().message().find("no PEM block"), std::string::npos) << s.status();
  // Issue 33, item 9: a key that is not the certificate's was reported as "the port is in use".
  config.tls_cert = tmp_.File("server.pem");
  config.tls_key = tmp_.File("client.key");
  s = server::LifemapServer::Start(config);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.status().message().find("does not belong to the certificate"), std::string::npos)
      << s.status();
  EXPECT_EQ(s.status().message().find("in use"), std::string::npos) << s.status();
}

}  // namespace
}  // namespace lifemap
