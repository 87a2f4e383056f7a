# Debian builds ITK with GCC, and its itk_compiler_detection.h knows only GCC ("Unsupported
# compiler" under clang). The fuzz build (clang, for libFuzzer) includes ITK through a shim: a
# folder of links to every ITK header, where the detection header says what this clang supports
# (C++17: every feature ITK asks about) instead. Only CREPUSCULAR_FUZZ builds use it.
function(crepuscular_itk_clang_shim out_var)
  set(itk_dir "")
  foreach(dir IN LISTS ITK_INCLUDE_DIRS)
    if(EXISTS "${dir}/itk_compiler_detection.h")
      set(itk_dir "${dir}")
    endif()
  endforeach()
  if(NOT itk_dir)
    message(FATAL_ERROR "ITK's itk_compiler_detection.h not found in ${ITK_INCLUDE_DIRS}")
  endif()
  get_filename_component(itk_name "${itk_dir}" NAME)
  set(shim "${CMAKE_BINARY_DIR}/itk-clang-shim/${itk_name}")
  file(MAKE_DIRECTORY "${shim}/compilers")
  file(GLOB entries RELATIVE "${itk_dir}" "${itk_dir}/*" "${itk_dir}/compilers/*")
  foreach(entry IN LISTS entries)
    if(entry STREQUAL "compilers" OR entry STREQUAL "itk_compiler_detection.h")
      continue()
    endif()
    if(NOT EXISTS "${shim}/${entry}")
      file(CREATE_LINK "${itk_dir}/${entry}" "${shim}/${entry}" SYMBOLIC)
    endif()
  endforeach()
  file(READ "${itk_dir}/itk_compiler_detection.h" detection)
  string(REPLACE "#  if ITK_COMPILER_IS_GNU\n"
                 "#  if ITK_COMPILER_IS_GNU || ITK_COMPILER_IS_Clang\n" detection "${detection}")
  file(WRITE "${shim}/itk_compiler_detection.h" "${detection}")
  # GCC's feature table, read as GCC 12 would: clang (which says it is GCC 4.2) has them all.
  file(READ "${itk_dir}/compilers/ITK_COMPILER_INFO_GNU_CXX.h" info)
  string(REPLACE "(__GNUC__ * 10000 + __GNUC_MINOR__ * 100 + __GNUC_PATCHLEVEL__)" "120200"
                 info "${info}")
  string(REPLACE "(__GNUC__ * 100 + __GNUC_MINOR__)" "1202" info "${info}")
  file(WRITE "${shim}/compilers/ITK_COMPILER_INFO_GNU_CXX.h" "${info}")
  set(${out_var} "${shim}" PARENT_SCOPE)
endfunction()
