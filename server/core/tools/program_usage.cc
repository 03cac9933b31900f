#include "program_usage.h"

#ifdef __linux__
#include <sys/prctl.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <iostream>

#include "absl/flags/parse.h"
#include "absl/flags/reflection.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace mll::core::tools {
namespace {

#ifndef MLL_PROJECT_VERSION
#error "MLL_PROJECT_VERSION must be defined (server/core/CMakeLists.txt)"
#endif

constexpr int kExitUsage = 2;

absl::string_view Basename(absl::string_view path) {
  const size_t slash = path.rfind('/');
  return slash == absl::string_view::npos ? path : path.substr(slash + 1);
}

bool IsHelpFlag(absl::string_view word) {
  for (absl::string_view help : {"--help", "-help", "-h", "--helpfull",
                                 "-helpfull", "--helpshort", "-helpshort"}) {
    if (word == help) return true;
  }
  return false;
}

}  // namespace

std::vector<const absl::CommandLineFlag*> FlagsDefinedIn(
    absl::string_view source_basename) {
  std::vector<const absl::CommandLineFlag*> flags;
  for (const auto& [name, flag] : absl::GetAllFlags()) {
    if (Basename(flag->Filename()) == source_basename) flags.push_back(flag);
  }
  std::sort(flags.begin(), flags.end(),
            [](const absl::CommandLineFlag* a, const absl::CommandLineFlag* b) {
              return a->Name() < b->Name();
            });
  return flags;
}

std::vector<const absl::CommandLineFlag*> FlagsNamed(
    const std::vector<absl::string_view>& names) {
  std::vector<const absl::CommandLineFlag*> flags;
  for (absl::string_view name : names) {
    const absl::CommandLineFlag* flag = absl::FindCommandLineFlag(name);
    if (flag == nullptr) {
      std::fprintf(stderr, "program_usage: no flag --%.*s\n",
                   static_cast<int>(name.size()), name.data());
      std::abort();
    }
    flags.push_back(flag);
  }
  return flags;
}

std::string DescribeFlags(
    const std::vector<const absl::CommandLineFlag*>& flags) {
  std::string text;
  for (const absl::CommandLineFlag* flag : flags) {
    const std::string default_value = flag->DefaultValue();
    absl::StrAppend(&text, "  --", flag->Name(), "=",
                    default_value.empty() ? "\"\"" : default_value, "\n");
    for (absl::string_view line : absl::StrSplit(flag->Help(), '\n')) {
      absl::StrAppend(&text, "      ", line, "\n");
    }
  }
  return text;
}

std::vector<std::string> ParseCommandLine(
    int argc, char** argv,
    absl::FunctionRef<std::string(const std::vector<std::string>&)> help) {
  bool wants_help = false;
  bool wants_version = false;
  std::vector<std::string> words;
  for (int i = 1; i < argc; ++i) {
    const absl::string_view word = argv[i];
    if (IsHelpFlag(word)) {
      wants_help = true;
    } else if (word == "--version" || word == "-version") {
      wants_version = true;
    } else if (!absl::StartsWith(word, "-")) {
      words.emplace_back(word);
    }
  }
  if (wants_help) {
    std::cout << help(words) << std::flush;
    std::exit(0);
  }
  if (wants_version) {
    std::cout << Basename(argv[0]) << " " << MLL_PROJECT_VERSION << std::endl;
    std::exit(0);
  }
  std::vector<char*> positional = absl::ParseCommandLine(argc, argv);
  return std::vector<std::string>(positional.begin() + 1, positional.end());
}

void ParseFlagsOnly(int argc, char** argv, absl::string_view program,
                    absl::FunctionRef<std::string()> help) {
  const std::vector<std::string> positional = ParseCommandLine(
      argc, argv, [&](const std::vector<std::string>&) { return help(); });
  if (!positional.empty()) {
    std::cerr << program << ": takes flags only (--name=value); got \""
              << absl::StrJoin(positional, " ") << "\"; see " << program
              << " --help" << std::endl;
    std::exit(kExitUsage);
  }
}

absl::Status FollowParent(int64_t parent_pid, absl::string_view program) {
  if (parent_pid < 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--parent_pid: ", parent_pid,
        " is out of range: allowed 0 (off) or the pid of the process that "
        "started ",
        program));
  }
#ifdef __linux__
  if (parent_pid > 0) {
    prctl(PR_SET_PDEATHSIG, SIGTERM);
    // The parent may have exited before the line above took effect.
    if (getppid() != parent_pid) {
      return absl::FailedPreconditionError(absl::StrCat(
          "--parent_pid=", parent_pid, " has already exited; not starting"));
    }
  }
#endif
  return absl::OkStatus();
}

}  // namespace mll::core::tools
