# Extracts the C++ and CMake code blocks of README.md and docs/*.md, so that
# the consumer_package test builds them against the installed package.
#   cmake -DSOURCE_ROOT=<repository> -DOUT_DIR=<folder> -P doc_blocks.cmake
# writes into OUT_DIR:
#   doc_block_<k>.cc  one per ```cpp block: as written when it defines main(),
#                     else its #include lines, then the rest of it as the body
#                     of a function, and a main() that does nothing (a block
#                     is compiled and linked, not run);
#   doc_blocks.cmake  an executable per .cc file linked with mll::client, then
#                     each ```cmake block as written, after an executable for
#                     each target it names with target_link_libraries that is
#                     not yet defined;
#   blocks.txt        "document:line" of every block extracted, one a line
#                     (client_py/tests/test_readme.py compares it with its own
#                     parser's list).
# A block is left out when the line above its fence is the marker
# <!-- test: skip REASON -->, as client_py/tests/test_readme.py documents.
cmake_minimum_required(VERSION 3.16)
foreach(input SOURCE_ROOT OUT_DIR)
  if(NOT DEFINED ${input})
    message(FATAL_ERROR "doc_blocks.cmake: -D${input}=... is required")
  endif()
endforeach()

file(REMOVE_RECURSE ${OUT_DIR})
file(MAKE_DIRECTORY ${OUT_DIR})
file(GLOB docs RELATIVE ${SOURCE_ROOT} ${SOURCE_ROOT}/docs/*.md)
list(SORT docs)
set(documents README.md CHANGELOG.md ${docs})

# Markdown text holds ';', '[' and ']', which CMake lists treat specially: they
# are replaced by placeholders while the text is split into lines, and put
# back in what is written.
function(restore out text)
  string(REPLACE "@MLL_SEMICOLON@" ";" text "${text}")
  string(REPLACE "@MLL_OPEN@" "[" text "${text}")
  string(REPLACE "@MLL_CLOSE@" "]" text "${text}")
  set(${out} "${text}" PARENT_SCOPE)
endfunction()

set(count 0)
set(listed "")
set(targets_cmake "")
set(cmake_blocks "")
foreach(document IN LISTS documents)
  if(NOT EXISTS ${SOURCE_ROOT}/${document})
    continue()
  endif()
  file(READ ${SOURCE_ROOT}/${document} text)
  string(REPLACE ";" "@MLL_SEMICOLON@" text "${text}")
  string(REPLACE "[" "@MLL_OPEN@" text "${text}")
  string(REPLACE "]" "@MLL_CLOSE@" text "${text}")
  string(REPLACE "\n" ";" lines "${text}")
  set(number 0)
  set(language "")
  set(previous "")
  foreach(line IN LISTS lines)
    math(EXPR number "${number} + 1")
    if(language STREQUAL "")
      if(line MATCHES "^```")
        string(REGEX REPLACE "^```[ \t]*([^ \t]*).*$" "\\1" language "${line}")
        if(language STREQUAL "")
          set(language "none")
        endif()
        set(start ${number})
        set(skip OFF)
        if(previous MATCHES "^[ \t]*<!--[ \t]*test:[ \t]*skip")
          set(skip ON)
        endif()
        set(includes "")
        set(body "")
        set(whole OFF)
      elseif(NOT line MATCHES "^[ \t]*$")
        set(previous "${line}")
      endif()
      continue()
    endif()
    if(NOT line MATCHES "^```[ \t]*$")
      if(language STREQUAL "cpp" AND line MATCHES "^#include")
        string(APPEND includes "${line}\n")
      else()
        string(APPEND body "${line}\n")
      endif()
      if(line MATCHES "int main\\(")
        set(whole ON)
      endif()
      continue()
    endif()
    # The closing fence.
    if(NOT skip AND language MATCHES "^(cpp|cmake)$")
      string(APPEND listed "${document}:${start}\n")
      if(language STREQUAL "cpp")
        math(EXPR count "${count} + 1")
        set(file doc_block_${count}.cc)
        set(source "// ${document}:${start}\n")
        if(whole)
          string(APPEND source "${includes}${body}")
        else()
          string(APPEND source "#include <cstdint>\n#include <string>\n"
            "#include <vector>\n\n#include \"mll/client.h\"\n${includes}\n"
            "namespace {\n[[maybe_unused]] void DocBlock() {\n"
            "${body}}\n}  // namespace\n\nint main() { return 0; }\n")
        endif()
        restore(source "${source}")
        file(WRITE ${OUT_DIR}/${file} "${source}")
        string(APPEND targets_cmake
          "add_executable(doc_block_${count} \${CMAKE_CURRENT_LIST_DIR}/${file})\n"
          "target_link_libraries(doc_block_${count} PRIVATE mll::client)\n")
      else()
        restore(block "${body}")
        string(REGEX MATCHALL "target_link_libraries\\([ \t]*[A-Za-z0-9_]+" named
          "${block}")
        foreach(call IN LISTS named)
          string(REGEX REPLACE ".*\\([ \t]*" "" target "${call}")
          string(APPEND cmake_blocks "if(NOT TARGET ${target})\n"
            "  add_executable(${target} \${CMAKE_CURRENT_LIST_DIR}/empty_main.cc)\n"
            "endif()\n")
        endforeach()
        string(APPEND cmake_blocks "# ${document}:${start}\n${block}")
      endif()
    endif()
    set(language "")
    set(previous "")
  endforeach()
endforeach()

file(WRITE ${OUT_DIR}/empty_main.cc
  "#include \"mll/client.h\"\n\nint main() {\n"
  "  return mll::client::LanderOutcomeName(\n"
  "             mll::client::LanderOutcome::kLanded).empty();\n}\n")
file(WRITE ${OUT_DIR}/doc_blocks.cmake "${targets_cmake}${cmake_blocks}")
file(WRITE ${OUT_DIR}/blocks.txt "${listed}")
