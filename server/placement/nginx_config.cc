#include "server/placement/nginx_config.h"

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "core/common/cluster_headers.h"

namespace lifemap::placement {
namespace {

// Upstream group names: a prefix keeps a shard's name from meeting nginx's own words.
std::string Upstream(const std::string& shard) { return "lifemap_shard_" + shard; }
constexpr const char* kNewMaps = "lifemap_new_maps";

// Names and addresses are validated ([A-Za-z0-9._-], HOST:PORT); quoting still keeps a stray
// character from breaking the file.
std::string Quoted(const std::string& s) {
  return absl::StrCat("\"", absl::StrReplaceAll(s, {{"\\", "\\\\"}, {"\"", "\\\""}}), "\"");
}

// A map's key in the `map $http_lifemap_map` block: the header's encoded form (the name's
// bytes outside [A-Za-z0-9._-] percent-encoded, as the clients send it), with nginx's special
// words (a map called "default") escaped by a backslash, as the map module asks.
std::string MapKey(const std::string& name) {
  std::string key = EncodeHeaderValue(name);
  if (key == "default" || key == "hostnames" || key == "include" || key == "volatile")
    key = "\\" + key;
  return key;
}

}  // namespace

std::string NginxConfig(const std::vector<Shard>& shards, const std::vector<MapPlacement>& maps,
                        const NginxOptions& options) {
  std::string http;
  const auto line = [&](const std::string& indent, const std::string& text) {
    absl::StrAppend(&http, indent, text, "\n");
  };
  line("", "# Written by `lifemap admin shards nginx-config` from the placement database.");
  line("", "# Do not edit: regenerate after adding or draining a shard or moving a map.");
  for (const Shard& s : shards) {
    line("", absl::StrCat("upstream ", Upstream(s.name), " {"));
    line("  ", absl::StrCat("server ", s.address, " max_fails=0;"));
    line("  ", "keepalive 16;");
    line("", "}");
  }
  // New maps: hashed over the active shards (all of them if every shard drains).
  int active = 0;
  for (const Shard& s : shards) active += s.state == "active" ? 1 : 0;
  line("", absl::StrCat("upstream ", kNewMaps, " {"));
  line("  ", "hash $http_lifemap_map consistent;");
  for (const Shard& s : shards) {
    if (s.state == "active" || active == 0) {
      line("  ", absl::StrCat("server ", s.address, " max_fails=0;"));
    }
  }
  if (shards.empty()) line("  ", "server 127.0.0.1:1 down;  # no shard yet");
  line("", "}");

  line("", "map $http_lifemap_shard $lifemap_by_shard {");
  line("  ", "default \"\";");
  for (const Shard& s : shards)
    line("  ", absl::StrCat(Quoted(s.name), " ", Upstream(s.name), ";"));
  line("", "}");
  line("", "map $http_lifemap_map $lifemap_by_map {");
  line("  ", "default \"\";");
  for (const MapPlacement& m : maps) {
    // A map being moved is served by its source until the switch, then by its target: the
    // placement's `shard` says which.
    line("  ", absl::StrCat(Quoted(MapKey(m.map)), " ", Upstream(m.shard), ";"));
  }
  line("", "}");
  line("", "map \"$lifemap_by_shard|$lifemap_by_map\" $lifemap_upstream {");
  line("  ", "\"~^(?<lifemap_s>[^|]+)\\|\" $lifemap_s;");
  line("  ", "\"~^\\|(?<lifemap_m>.+)$\" $lifemap_m;");
  line("  ", absl::StrCat("default ", kNewMaps, ";"));
  line("", "}");
  line("", "map $lifemap_upstream $lifemap_unreachable {");
  for (const Shard& s : shards) {
    line("  ", absl::StrCat(Upstream(s.name), " ",
                            Quoted(absl::StrCat("shard ", s.name, " (", s.address,
                                                ") is unreachable: its maps are unavailable "
                                                "until it is back; other shards are unaffected")),
                            ";"));
  }
  line("  ", absl::StrCat("default ", Quoted("no shard is reachable for a new map"), ";"));
  line("", "}");

  const std::string timeout = absl::StrCat(static_cast<int>(options.stream_timeout_s), "s");
  line("", "server {");
  const bool tls = !options.tls_cert.empty();
  line("  ", absl::StrCat("listen ", options.listen, tls ? " ssl" : "", " http2;"));
  if (tls) {
    line("  ", absl::StrCat("ssl_certificate ", options.tls_cert, ";"));
    line("  ", absl::StrCat("ssl_certificate_key ", options.tls_key, ";"));
  }
  line("  ", "client_max_body_size 0;  # frame streams are long request bodies");
  line("  ", absl::StrCat("client_body_timeout ", timeout, ";"));
  line("  ", absl::StrCat("keepalive_timeout ", timeout, ";"));
  line("  ", "http2_max_concurrent_streams 1024;");
  line("  ", "location / {");
  line("    ", "grpc_pass grpc://$lifemap_upstream;");
  line("    ", absl::StrCat("grpc_set_header ", kRoutedByHeader, " nginx;"));
  line("    ", absl::StrCat("grpc_read_timeout ", timeout, ";"));
  line("    ", absl::StrCat("grpc_send_timeout ", timeout, ";"));
  line("    ", "grpc_socket_keepalive on;");
  line("    ", "error_page 502 503 504 = @lifemap_unreachable;");
  line("  ", "}");
  // A gRPC answer nginx writes itself: trailers-only, UNAVAILABLE (14) naming the shard.
  line("  ", "location @lifemap_unreachable {");
  line("    ", "default_type application/grpc;");
  line("    ", "add_header grpc-status 14 always;");
  line("    ", "add_header grpc-message $lifemap_unreachable always;");
  line("    ", "return 200;");
  line("  ", "}");
  line("", "}");

  if (!options.standalone) return http;
  std::string conf;
  const std::string& p = options.prefix;
  absl::StrAppend(&conf, "# nginx -p ", p, " -c THIS_FILE\n");
  absl::StrAppend(&conf, "worker_processes 1;\n");
  absl::StrAppend(&conf, "pid ", p, "/nginx.pid;\n");
  absl::StrAppend(&conf, "error_log ", p, "/error.log warn;\n");
  absl::StrAppend(&conf, "events { worker_connections 4096; }\n");
  absl::StrAppend(&conf, "http {\n");
  absl::StrAppend(&conf, "access_log off;\n");
  for (const char* temp : {"client_body", "proxy", "fastcgi", "uwsgi", "scgi"}) {
    absl::StrAppend(&conf, temp, "_temp_path ", p, "/", temp, "_temp;\n");
  }
  absl::StrAppend(&conf, http, "}\n");
  return conf;
}

}  // namespace lifemap::placement
