// The browser view's static files (server/http/www, and three.js from Debian's libjs-three),
// built into lifemapd by cmake/EmbedAssets.cmake: the pages need no files beside the binary
// and no network.
#pragma once

#include <cstddef>
#include <string>

namespace lifemap::server::web {

struct WebAsset {
  const char* path;  // as requested, e.g. "/app.js"
  const char* data;
  size_t size;
  const char* content_type;
};

// The asset served at `path`, or null.
const WebAsset* FindWebAsset(const std::string& path);

}  // namespace lifemap::server::web
