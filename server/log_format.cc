#include "server/log_format.h"

#include <string>

#include <spdlog/pattern_formatter.h>
#include <spdlog/spdlog.h>

#include "core/common/utf8.h"

namespace lifemap::server {
namespace {

// spdlog's default pattern with the message's text escaped first.
class EscapingFormatter : public spdlog::formatter {
 public:
  EscapingFormatter() : inner_(std::make_unique<spdlog::pattern_formatter>()) {}

  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    const absl::string_view text(msg.payload.data(), msg.payload.size());
    const std::string escaped = EscapeForLog(text);
    if (escaped.size() == text.size()) {  // nothing escaped (the usual case): no copy
      inner_->format(msg, dest);
      return;
    }
    spdlog::details::log_msg copy = msg;
    copy.payload = spdlog::string_view_t(escaped.data(), escaped.size());
    inner_->format(copy, dest);
    // Where a colour sink colours the level (mutable fields the pattern sets as it formats).
    msg.color_range_start = copy.color_range_start;
    msg.color_range_end = copy.color_range_end;
  }

  std::unique_ptr<spdlog::formatter> clone() const override {
    return std::make_unique<EscapingFormatter>();
  }

 private:
  std::unique_ptr<spdlog::formatter> inner_;
};

}  // namespace

void EscapeLogMessages(spdlog::logger* logger) {
  logger->set_formatter(std::make_unique<EscapingFormatter>());
}

void EscapeDefaultLogMessages() { EscapeLogMessages(spdlog::default_logger_raw()); }

}  // namespace lifemap::server
