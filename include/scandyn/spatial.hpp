// scandyn/spatial.hpp: the whole spatial algebra (host + device).
#pragma once

#include "scandyn/spatial/inertia.hpp"
#include "scandyn/spatial/motion.hpp"
#include "scandyn/spatial/quaternion.hpp"
#include "scandyn/spatial/scalar.hpp"
#include "scandyn/spatial/transform.hpp"
#include "scandyn/spatial/vec3.hpp"
