// What the browser view checks before routing a request (issue 52, item 8): that it was sent to
// this server by name (DNS rebinding: a page of another origin whose name an attacker points
// at 127.0.0.1 reaches a loopback view with its own Host), and that a request which changes
// state (POST, DELETE) comes from the view's own pages (cross-site requests: any page may send
// a `text/plain` POST, which a browser does not preflight). Pure functions over header values,
// so that they are tested without a server (tests/server/request_guard_test.cc).
#pragma once

#include <string>
#include <vector>
#include "absl/strings/string_view.h"

#include "absl/status/status.h"

namespace lifemap::server {

struct HostPolicy {
  // Names the view answers to besides IP literals and localhost: the listen address's host
  // when it is a name, this machine's host name, and `http_allowed_hosts` (config key, flag
  // --http-allowed-host). An entry ".example.org" takes every name under example.org; "*"
  // takes any name (a proxy in front that checks Host itself). Lower case.
  std::vector<std::string> names;
};

// The policy for a view listening on `listen_host` with `allowed` added (this machine's host
// name included).
HostPolicy MakeHostPolicy(const std::string& listen_host, const std::vector<std::string>& allowed);

// OK when `host` (a Host header's value: NAME, NAME:PORT, IPv4[:PORT] or [IPv6][:PORT]; empty
// when the request had none, as HTTP/1.0 allows) names this server; PERMISSION_DENIED saying
// which names it answers to otherwise.
absl::Status CheckHost(absl::string_view host, const HostPolicy& policy);

// For a request of `method`: OK for reads (GET, HEAD, OPTIONS). For the others,
// PERMISSION_DENIED when `sec_fetch_site` is present and neither "same-origin" nor "none" (a
// browser says so of a request another site's page made), or `origin` is present and not the
// view's own (its host[:port] differs from `host`); INVALID_ARGUMENT when a request with a
// body (`has_body`) is not `application/json` (a cross-site page can send only form and plain
// text types without a CORS preflight, which the view never grants).
absl::Status CheckStateChange(absl::string_view method, absl::string_view host,
                              absl::string_view origin, absl::string_view sec_fetch_site,
                              absl::string_view content_type, bool has_body);

}  // namespace lifemap::server
