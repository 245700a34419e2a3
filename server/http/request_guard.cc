#include "server/http/request_guard.h"

#include <arpa/inet.h>
#include <unistd.h>

#include <algorithm>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/common/utf8.h"

namespace lifemap::server {
namespace {

// The host part of a Host header or an origin's authority, lower case, without its port and
// trailing dot; an IPv6 literal keeps its brackets off.
std::string HostPart(absl::string_view authority) {
  absl::string_view host = authority;
  if (!host.empty() && host.front() == '[') {
    const size_t close = host.find(']');
    if (close == absl::string_view::npos) return "";  // malformed: names nothing
    host = host.substr(1, close - 1);
  } else if (std::count(host.begin(), host.end(), ':') == 1) {
    host = host.substr(0, host.find(':'));
  }
  std::string out = absl::AsciiStrToLower(host);
  while (!out.empty() && out.back() == '.') out.pop_back();
  return out;
}

bool IsIpLiteral(const std::string& host) {
  unsigned char buf[16];
  return inet_pton(AF_INET, host.c_str(), buf) == 1 || inet_pton(AF_INET6, host.c_str(), buf) == 1;
}

bool IsLocalhost(const std::string& host) {
  return host == "localhost" || absl::EndsWith(host, ".localhost");
}

bool Matches(const std::string& host, const std::string& entry) {
  if (entry == "*") return true;
  if (!entry.empty() && entry.front() == '.') {
    return host == entry.substr(1) || absl::EndsWith(host, entry);
  }
  return host == entry;
}

}  // namespace

HostPolicy MakeHostPolicy(const std::string& listen_host, const std::vector<std::string>& allowed) {
  HostPolicy policy;
  auto add = [&policy](const std::string& name) {
    std::string lower = HostPart(name);
    if (!lower.empty() && !IsIpLiteral(lower) &&
        std::find(policy.names.begin(), policy.names.end(), lower) == policy.names.end()) {
      policy.names.push_back(lower);
    }
  };
  add(listen_host);
  char hostname[256] = {};
  if (gethostname(hostname, sizeof(hostname) - 1) == 0) add(hostname);
  for (const auto& a : allowed) {
    // Kept as given: ".example.org" and "*" are patterns, not names.
    const std::string lower = absl::AsciiStrToLower(a);
    if (std::find(policy.names.begin(), policy.names.end(), lower) == policy.names.end()) {
      policy.names.push_back(lower);
    }
  }
  return policy;
}

absl::Status CheckHost(absl::string_view host_header, const HostPolicy& policy) {
  if (host_header.empty()) return absl::OkStatus();
  const std::string host = HostPart(host_header);
  if (!host.empty()) {
    if (IsIpLiteral(host) || IsLocalhost(host)) return absl::OkStatus();
    for (const auto& entry : policy.names) {
      if (Matches(host, entry)) return absl::OkStatus();
    }
  }
  return absl::PermissionDeniedError(absl::StrCat(
      "this browser view does not answer to the name '", EscapeForLog(host_header),
      "' (a page whose name points at this machine cannot read it): open it by its address or "
      "as localhost",
      policy.names.empty() ? "" : absl::StrCat(" or ", absl::StrJoin(policy.names, ", ")),
      ", or add the name with lifemapd --http-allowed-host NAME (config key "
      "http_allowed_hosts)"));
}

absl::Status CheckStateChange(absl::string_view method, absl::string_view host,
                              absl::string_view origin, absl::string_view sec_fetch_site,
                              absl::string_view content_type, bool has_body) {
  if (method == "GET" || method == "HEAD" || method == "OPTIONS") return absl::OkStatus();
  if (!sec_fetch_site.empty() && sec_fetch_site != "same-origin" && sec_fetch_site != "none") {
    return absl::PermissionDeniedError(absl::StrCat(
        "a ", method, " from another site's page (Sec-Fetch-Site: ", EscapeForLog(sec_fetch_site),
        ") is refused: change maps from the view's own pages or with the lifemap CLI"));
  }
  if (!origin.empty()) {
    const size_t scheme = origin.find("://");
    const absl::string_view authority =
        scheme == absl::string_view::npos ? absl::string_view() : origin.substr(scheme + 3);
    if (authority.empty() || !absl::EqualsIgnoreCase(authority, host)) {
      return absl::PermissionDeniedError(
          absl::StrCat("a ", method, " from the page of origin '", EscapeForLog(origin),
                       "' is refused: only the view's own pages (", EscapeForLog(host),
                       ") may change maps; or use the lifemap CLI"));
    }
  }
  if (has_body) {
    absl::string_view type = content_type.substr(0, content_type.find(';'));
    while (!type.empty() && type.back() == ' ') type.remove_suffix(1);
    if (!absl::EqualsIgnoreCase(type, "application/json")) {
      return absl::InvalidArgumentError(
          absl::StrCat("a ", method, " body must be JSON (Content-Type: application/json), not '",
                       EscapeForLog(content_type), "'"));
    }
  }
  return absl::OkStatus();
}

}  // namespace lifemap::server
