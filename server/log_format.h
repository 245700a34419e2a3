// Log lines that text from clients cannot forge (issue 52, item 11): a robot's name, a map's
// description, a refused call's text or an archive's map name with a newline or an ANSI escape
// wrote lines of their own into the server's log (and coloured or cleared the operator's
// terminal). Every message is escaped as it is formatted (core/common/utf8.h EscapeForLog:
// \n, \r, \t, \\, C0/C1 controls, DEL, bidi and zero-width characters and invalid UTF-8), so
// one event is one line whatever its text.
#pragma once

#include <memory>

namespace spdlog {
class logger;
}

namespace lifemap::server {

// Makes `logger` (every sink of it) escape each message's text, keeping its pattern
// ("[time] [name] [level] message", spdlog's default).
void EscapeLogMessages(spdlog::logger* logger);
// The same for spdlog's default logger (lifemapd's; LifemapServer::Start calls it).
void EscapeDefaultLogMessages();

}  // namespace lifemap::server
