// The bytes of examples/dqn/trained.qnet, compiled in (shipped_qnet.cc is
// generated from the file by client_cpp/CMakeLists.txt).
#ifndef MLL_CLIENT_TOOLS_SHIPPED_QNET_H_
#define MLL_CLIENT_TOOLS_SHIPPED_QNET_H_

#include <cstddef>

namespace mll::client {

extern const unsigned char kShippedQnet[];
extern const size_t kShippedQnetSize;

}  // namespace mll::client

#endif  // MLL_CLIENT_TOOLS_SHIPPED_QNET_H_
