// Reading a client stream's next message so that a message that does not parse is told apart
// from the stream's end. gRPC's Read returns false for both (issue 33: a garbage message
// mid-stream ended the stream with OK, and a StreamStart whose name held invalid UTF-8 was
// answered "stream closed before its StreamStart"). Protobuf clears a message before parsing
// into it, while the end of a stream leaves it untouched: a mark set in the message's unknown
// fields before the read survives only the end of the stream.
#pragma once

#include <google/protobuf/message.h>
#include <google/protobuf/unknown_field_set.h>

#include <type_traits>

namespace lifemap::server {

enum class ReadOutcome {
  kMessage,     // `message` holds the next message
  kEnd,         // the client closed its side (or the call ended)
  kUnparsable,  // a message arrived that does not parse (most often invalid UTF-8 in a string)
};

template <typename Stream, typename Message>
ReadOutcome ReadMessage(Stream* stream, Message* message) {
  static_assert(std::is_base_of_v<google::protobuf::Message, Message>);
  // The largest field number protobuf allows: no lifemap message uses it.
  constexpr int kUnreadMark = (1 << 29) - 1;
  message->Clear();
  message->GetReflection()->MutableUnknownFields(message)->AddVarint(kUnreadMark, 1);
  if (stream->Read(message)) return ReadOutcome::kMessage;
  const auto& unknown = message->GetReflection()->GetUnknownFields(*message);
  for (int i = 0; i < unknown.field_count(); ++i) {
    if (unknown.field(i).number() == kUnreadMark) return ReadOutcome::kEnd;
  }
  return ReadOutcome::kUnparsable;
}

}  // namespace lifemap::server
