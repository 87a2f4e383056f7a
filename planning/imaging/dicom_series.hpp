// The slices of a DICOM series folder, checked before ITK reads their voxels: every file a
// readable DICOM slice, one series (or the one chosen), no slice short of its pixel data, none
// there twice, none missing between the others.
#pragma once

#include <string>
#include <vector>

namespace crepuscular::planning {

// The slice files of the series to read from `folder`, ordered along the slice normal (row x
// column direction), as ITK's series reader takes them. `chosen`: SeriesInstanceUIDs (0020,000E)
// a user chose; a folder holding several series is read as the one of them listed here, a folder
// of one series as that one. Hidden files and DICOMDIR are passed over.
// Throws Error naming the folder, and the slice file where one is at fault, when:
//  - a file is not a readable DICOM Part 10 file (no "DICM", an element running past the end of
//    the file, a damaged header);
//  - the folder holds several series and none is chosen (the message lists them);
//  - a slice's uncompressed pixel data are shorter than rows x columns x bytes x samples x frames
//    (compressed slices: their fragments must lie within the file; decoding is GDCM's);
//  - two slices share a position or a SOPInstanceUID, or differ in orientation or size;
//  - the slice positions along the normal are not evenly spaced (a missing slice): gaps must be
//    within 1 % (at least 0.01 mm) of the median gap.
std::vector<std::string> dicom_series_slices(const std::string& folder,
                                             const std::vector<std::string>& chosen);

}  // namespace crepuscular::planning
