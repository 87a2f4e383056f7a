// ITK code shared by planning's files (see itk_image.hpp).
#include "planning/imaging/itk_image.hpp"

#include <itkConnectedComponentImageFilter.h>

namespace crepuscular::planning {

ComponentLabels label_components(const itk::Image<uint8_t, 3>* mask, bool fully_connected) {
  using Filter =
      itk::ConnectedComponentImageFilter<itk::Image<uint8_t, 3>, itk::Image<uint32_t, 3>>;
  auto cc = Filter::New();
  cc->SetInput(mask);
  cc->SetFullyConnected(fully_connected);
  cc->Update();
  return {cc->GetOutput(), size_t(cc->GetObjectCount())};
}

}  // namespace crepuscular::planning
