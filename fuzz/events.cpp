// Event files (host/events/EVENTS.md): binary files from disk, possibly
// truncated or from elsewhere.
#include "fuzz/fuzz.h"
#include "host/events/event_file.h"

namespace prism::fuzz {

void events(const uint8_t* data, size_t size) {
  const std::string path = prism::fuzz::write_file(prism::fuzz::scratch() / "f.events", data, size);
  try {
    prism::EventReader r(path);
    prism::Event e;
    while (r.next(e)) {
    }
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(events)
