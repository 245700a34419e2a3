// A synthetic indoor world with exact ground truth (issue 3): a place made of a room footprint,
// walls with doors and windows, furniture and movable props, as plain data that the generator
// fills, the renderer ray-casts and the writer describes in scene.json.
//
// Frame: world z is up, metres; the floor is z = 0. Cameras follow TUM: x right, y down,
// z forward, poses T_world_camera.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>

namespace lifemap::sim {

// Class ids written to labels/ (8-bit PNG). 0 = no surface (missing depth or sky through a
// window).
enum class SemanticClass : uint8_t {
  kNone = 0,
  kFloor = 1,
  kWall = 2,
  kCeiling = 3,
  kDoor = 4,
  kWindow = 5,
  kTable = 6,
  kShelf = 7,
  kCabinet = 8,
  kBed = 9,
  kSofa = 10,
  kChair = 11,
  kBox = 12,
  kCylinder = 13,
  kBook = 14,
  kMug = 15,
  kClutter = 16,
  kPerson = 17,
  kStairs = 18,
  // Curved and crumpled props (issue 13): the surfaces whose normals scatter.
  kPlant = 19,
  kBag = 20,
  kClothes = 21,
  kBall = 22,
  kLamp = 23,
  kBottle = 24,
};
constexpr int kClassCount = 25;
const char* ClassName(SemanticClass c);

// Whether objects of the class get moved between visits (chairs, props, people): the oracle's
// movable set.
bool MovableClass(SemanticClass c);

enum class OpeningType { kDoor, kWindow };

// A door or window in a wall segment, in metres along the wall from its start corner.
struct Opening {
  OpeningType type = OpeningType::kDoor;
  int room = 0;           // 0 = the main room (footprint), k = adjoining_rooms[k - 1]
  int wall = 0;           // index of the wall segment (corner i to corner i+1) in that room
  bool connects = false;  // a door between two rooms of the place (its twin is in the other
                          // room's shared wall); open, it shows the other room
  double offset_m = 0;    // from the wall's start to the opening's near edge
  double width_m = 0.9;
  double sill_m = 0;   // bottom: 0 for doors, ~1.2 for windows
  double top_m = 2.1;  // top: 2.10 m for doors and windows (paper 004's norms)
  bool open = true;    // doors: open shows the next space (rendered as far void);
                       // closed doors are a panel flush with the wall
};

// A solid standing on `base_z`, rotated by yaw about z:
// - kBox: an upright box; size = x, y, height.
// - kCylinder: an upright cylinder; size = diameter, -, height.
// - kBlob: an ellipsoid of diameters size.x, size.y and height size.z whose radius is
//   displaced by up to `crumple` (relative) with 3D value noise of `crumple_frequency` cycles
//   around it: 0 is a smooth ball or egg, 0.1 a bag, 0.3 foliage or a heap of clothes. Its
//   centre is `sink_m` lower than resting on base_z (a dome: the surface below hides the rest).
// - kLathe: a surface of revolution about the vertical axis: `profile` holds (height above
//   base_z, radius) in metres from (0, 0) to (top, 0), heights never decreasing (a bottle, a
//   lamp, a pot); size = 2 x largest radius, the same, top height.
struct Solid {
  enum class Shape { kBox, kCylinder, kBlob, kLathe } shape = Shape::kBox;
  SemanticClass cls = SemanticClass::kBox;
  int instance = 0;      // unique within the place, > 0; the parts of one object share it
  int group = 0;         // > 0: solids that move, appear and vanish together (a plant's pot and
                         // foliage, a stack of clutter); 0: on its own
  bool movable = false;  // props move between visits; furniture rarely
  Eigen::Vector2d center{0, 0};
  double base_z = 0;
  double yaw = 0;                        // radians
  Eigen::Vector3d size{0.3, 0.3, 0.3};   // see the shapes above
  double crumple = 0;                    // kBlob only
  double crumple_frequency = 3;          // kBlob only
  double sink_m = 0;                     // kBlob only
  std::vector<Eigen::Vector2d> profile;  // kLathe only
  uint32_t texture_seed = 1;
  Eigen::Vector3f color{0.6f, 0.5f, 0.4f};  // base albedo, RGB in [0, 1]
};

// How far a kBlob's surface can reach, relative to its unit ellipsoid: 1 + crumple and a 2 %
// margin, so that a sphere of this radius starts every ray march outside the surface.
inline double BlobReach(const Solid& s) { return 1.02 * (1 + s.crumple); }

// The lowest and highest points a solid can reach (metres, world z): its bounds for culling.
std::pair<double, double> VerticalExtent(const Solid& s);

// How a surface looks: the procedural texture the renderer paints on it.
struct Finish {
  uint32_t texture_seed = 1;
  Eigen::Vector3f albedo{0.5f, 0.5f, 0.5f};  // RGB in [0, 1]
  double texture_scale = 1.0;                // pattern frequency, relative (higher: finer)
  float contrast = 1.0f;                     // of the noise pattern (paint: low)
  bool prints = true;                        // printed patches (darker and brighter cells)
  double tile_m = 0;  // > 0: square tiles of this side with grout lines between them,
                      // every tile the same pattern (a floor covering)
};

// The finishes of a place's fixed surfaces.
struct Materials {
  Finish floor, ceiling, wall;
  bool wall_per_segment = true;  // each wall segment its own texture seed (wall.texture_seed +
                                 // its index); false: one paint for every wall
};

// How places are furnished and finished (`lifemap sim --world`).
struct PlaceStyle {
  // Props: false = boxes, cylinders, mugs, books and a clutter heap (the first world, issue 3);
  // true = also curved and crumpled ones: plants, bags, clothes heaps, balls, lamps, bottles
  // and stacked clutter.
  bool curved_props = false;
  // 0: every place has its own floor, paint and furniture textures. Otherwise places made with
  // the same building seed share one tiled floor covering, one wall paint and the same
  // furniture models (tables, chairs, shelves, cabinets, sofas, beds), as rooms of one building
  // do; they still differ in shape, layout and clutter.
  uint64_t building_seed = 0;
};

// A straight flight of stairs. Going up: `steps` boxes on the floor, each `rise_m` higher than
// the one before. Going down: a hole in the floor with the steps below floor level.
struct Stairs {
  bool up = true;
  Eigen::Vector2d origin{0, 0};  // centre of the first step's near edge, on the floor
  double yaw = 0;                // direction of travel (up or down the flight), radians
  double width_m = 1.0;
  double run_m = 0.28;   // tread depth
  double rise_m = 0.17;  // riser height
  int steps = 6;
};

struct Place;
// The footprint of room `index` (0 = main).
const std::vector<Eigen::Vector2d>& RoomFootprint(const Place& place, int index);

// Plane geometry of footprints (metres, world x-y).
bool InsidePolygon(const std::vector<Eigen::Vector2d>& polygon, double x, double y);
// Distance from p to the nearest edge of the (closed) polygon.
double DistanceToEdges(const std::vector<Eigen::Vector2d>& polygon, const Eigen::Vector2d& p);

// The radius of a circle around a solid's footprint (boxes: half the diagonal).
double FootprintRadius(const Solid& s);

struct Place {
  std::string id;                          // e.g. "place-7-L"
  std::string shape;                       // rect, square, L, T, U
  std::vector<Eigen::Vector2d> footprint;  // counter-clockwise corners of the main room, metres
  // Further rooms, each sharing a wall (and a connecting door) with the main room.
  std::vector<std::vector<Eigen::Vector2d>> adjoining_rooms;
  double wall_height_m = 2.7;
  std::vector<Opening> openings;
  std::vector<Solid> solids;  // furniture and props (and the steps of stairs, class kStairs)
  std::vector<Stairs> stairs;
  uint32_t texture_seed = 1;
  Materials materials;
  PlaceStyle style;
};

// Lighting of one visit: global brightness and colour temperature gain.
struct Lighting {
  double brightness = 1.0;                 // multiplies albedo
  Eigen::Vector3f tint{1.0f, 1.0f, 1.0f};  // RGB gain (warm/cool light)
  bool lamp_on = false;                    // a warm point light (a standing lamp)
  Eigen::Vector3d lamp{0, 0, 1.7};         // its position, world frame
  double lamp_power = 1.2;                 // irradiance gain at 1 m
};

}  // namespace lifemap::sim
