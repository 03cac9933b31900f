// Command-line help shared by mll_rollout, mll_server and mll_cli: `--help`
// lists the program's own flags by name, default and description (never
// abseil's internal flags or the paths of the files that define them) and
// exits 0, `--version` prints "<program> <version>" (the project's version,
// CMake's PROJECT_VERSION, as GetServerInfo's server_version and the Python
// package's) and exits 0, and positional arguments are refused where a program
// takes none.
// Also --parent_pid's rule for the programs that a client or a benchmark
// starts (mll_server, delay_proxy).
#ifndef MLL_CORE_TOOLS_PROGRAM_USAGE_H_
#define MLL_CORE_TOOLS_PROGRAM_USAGE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/flags/commandlineflag.h"
#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace mll::core::tools {

// The flags defined in the source file with this base name (e.g.
// "config_flags.cc"), sorted by name.
std::vector<const absl::CommandLineFlag*> FlagsDefinedIn(
    absl::string_view source_basename);

// The flags with these names, in this order; a name that is not a flag is a
// bug in the caller and aborts.
std::vector<const absl::CommandLineFlag*> FlagsNamed(
    const std::vector<absl::string_view>& names);

// One block per flag: "  --name=DEFAULT" and its description indented below.
std::string DescribeFlags(
    const std::vector<const absl::CommandLineFlag*>& flags);

// absl::ParseCommandLine, except that --help, -h, --helpfull and --helpshort
// print help(arguments) to stdout and exit 0, --version prints the program's
// name and the project's version and exits 0, where `arguments` are the
// command line's words that are not flags. Returns the positional arguments
// (argv[0] excluded).
std::vector<std::string> ParseCommandLine(
    int argc, char** argv,
    absl::FunctionRef<std::string(const std::vector<std::string>&)> help);

// ParseCommandLine for a program that takes flags only: any positional
// argument is a usage error (a one-line message on stderr, exit 2).
void ParseFlagsOnly(int argc, char** argv, absl::string_view program,
                    absl::FunctionRef<std::string()> help);

// --parent_pid=`parent_pid`: with a pid (> 0) the program gets SIGTERM when
// that process, its parent, dies (Linux). Called by the program itself, not
// between the parent's fork and exec: a forked child of a multi-threaded
// parent must do nothing before exec. INVALID_ARGUMENT for a negative pid,
// FAILED_PRECONDITION when the parent has already exited; 0 is off.
absl::Status FollowParent(int64_t parent_pid, absl::string_view program);

}  // namespace mll::core::tools

#endif  // MLL_CORE_TOOLS_PROGRAM_USAGE_H_
