# crepuscular_library(NAME SOURCES ... [PUBLIC ...] [PRIVATE ...]): one library target of ours,
# sources relative to the calling folder, includes from the project root, warnings on.
function(crepuscular_library name)
  cmake_parse_arguments(ARG "" "" "SOURCES;PUBLIC;PRIVATE" ${ARGN})
  add_library(${name} ${ARG_SOURCES})
  target_include_directories(${name} PUBLIC ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PUBLIC ${ARG_PUBLIC} PRIVATE ${ARG_PRIVATE})
  target_compile_options(${name} PRIVATE ${CREPUSCULAR_WARNINGS})
  target_compile_definitions(${name} PRIVATE CREPUSCULAR_VERSION="${PROJECT_VERSION}")
endfunction()
