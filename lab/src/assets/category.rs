//! The object categories the benchmark renders, where each one's 3D models come from, which of
//! them are source models and which are held out for the `shape` domain, and how each model is
//! put into the canonical frame of BENCHMARK.md §2 (z up, front facing −y, centred on the
//! bounding box) and normalised.

use anyhow::{Context, Result, bail};
use serde::Serialize;
use udapose_engine::UpSymmetry;

use super::flightgear::{self, Front, Model};
use super::mesh::TexturedMesh;
use super::{Assets, SHAPE_CARS, SOURCE_CARS, car::Car, sweethome};
use Front::{NegX, NegZ, PosX, PosZ};

/// A PASCAL3D+ category.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Category {
    Car,
    Aeroplane,
    Bus,
    Chair,
    Sofa,
    Diningtable,
}

/// Aeroplanes of the source domain: airliners, regional jets, light aircraft, a fighter.
const SOURCE_AEROPLANES: [Model; 12] = [
    fg("Aircraft/A320-iberia", NegX),
    fg("Aircraft/Boeing_737_800-american", NegZ),
    fg("Aircraft/Boeing_747_400-virgin", NegZ),
    fg("Aircraft/Boeing_757_200-delta", NegZ),
    fg("Aircraft/Boeing_767-300-delta", NegZ),
    fg("Aircraft/Boeing_777_300ER-emirates", NegZ),
    fg("Aircraft/Bombardier_CRJ700-deltacon", NegZ),
    fg("Aircraft/Embraer_175-aircanexp", NegZ),
    fg("Aircraft/Cessna172_red", NegX),
    fg("Aircraft/DR400-blue", PosX),
    fg("Aircraft/dhc6_lowpoly", NegX),
    fg("Aircraft/f16_lowpoly", NegX),
];
/// Aeroplanes of the `shape` domain: other families (an A380, a T-tail, a turboprop, a military
/// transport, a delta wing, a low-wing single).
const SHAPE_AEROPLANES: [Model; 6] = [
    fg("Aircraft/A380-ba", NegZ),
    fg("Aircraft/MD_88-delta", NegZ),
    fg("Aircraft/atr42-airfrance", NegZ),
    fg("Aircraft/c130-herc-obj1-ba", NegX),
    fg("Aircraft/m2000-5_lowpoly", NegX),
    fg("Aircraft/PiperCherokee140", NegZ),
];
const SOURCE_BUSES: [Model; 8] = [
    fg("Transport/tourbus1", NegZ),
    fg("Transport/110Bus", NegX),
    fg("Transport/bussmallwhite", NegZ),
    fg("Transport/minibuswhite1", NegZ),
    fg("Transport/bus-muc", NegX),
    fg("Airport/Vehicle/Cobus_2700s", NegX),
    fg("Airport/Vehicle/groundforce_bus", NegX),
    fg("Airport/Vehicle/lirq_cobus3000", PosZ),
];
const SHAPE_BUSES: [Model; 4] = [
    fg("Airport/Vehicle/Cobus_3000", NegX),
    fg("Airport/Vehicle/cobus2700-gen", NegZ),
    fg("Transport/bus-ba", PosZ),
    fg("Transport/bus_bi-ba", PosZ),
];

const fn fg(file: &'static str, front: Front) -> Model {
    Model { file, front }
}

/// The Sweet Home 3D libraries furniture is taken from (all CC0 or CC-BY 3.0; the `Reallusion`
/// one holds people).
const LIBRARIES: [&str; 4] = ["BlendSwap-CC-0", "BlendSwap-CC-BY", "KatorLegaz", "Scopia"];

impl Category {
    pub const ALL: [Category; 6] =
        [Category::Car, Category::Aeroplane, Category::Bus, Category::Chair, Category::Sofa, Category::Diningtable];

    pub fn name(self) -> &'static str {
        match self {
            Category::Car => "car",
            Category::Aeroplane => "aeroplane",
            Category::Bus => "bus",
            Category::Chair => "chair",
            Category::Sofa => "sofa",
            Category::Diningtable => "diningtable",
        }
    }

    /// The category called `name` (as [`Category::name`] spells it).
    pub fn from_name(name: &str) -> Option<Category> {
        Category::ALL.into_iter().find(|c| c.name() == name)
    }

    /// How `model` (its name in datasets) repeats itself about its up axis, read off
    /// `reports/syncar-preview/diningtable-orientation.png`: a dining table's long side is put to
    /// the front, so a rectangular one looks the same turned by 180°, a square one and a round top
    /// on four legs or feet by 90°, a round top on a round foot or under a cloth by any angle.
    /// The other categories have a front of their own.
    pub fn up_symmetry(self, model: &str) -> UpSymmetry {
        match (self, model) {
            (Category::Diningtable, "BlendSwap-CC-BY/cafe_set_mota_table" | "BlendSwap-CC-0/tableWithTablecloth") => {
                UpSymmetry::Continuous
            }
            (
                Category::Diningtable,
                "BlendSwap-CC-0/oakTable"
                | "BlendSwap-CC-BY/cafe_set_tonon_table"
                | "KatorLegaz/cafe-table"
                | "Scopia/round-table",
            ) => UpSymmetry::Order(4),
            (Category::Diningtable, _) => UpSymmetry::Order(2),
            _ => UpSymmetry::NONE,
        }
    }

    /// Whether a furniture catalogue's piece belongs to this category, after PASCAL VOC's
    /// definitions: chairs include armchairs and deck chairs, not wheelchairs, high chairs or
    /// stools; sofas include couches, not an unfolded sofa bed; dining tables are tables to eat
    /// at, told from coffee, bar, dressing or changing tables by their height (60-80 cm), without
    /// desks, games tables or glass tops (the renderer has no transparency).
    fn takes(self, piece: &sweethome::Piece) -> bool {
        let t = format!("{} {}", piece.title, piece.name).to_lowercase();
        let has = |words: &[&str]| words.iter().any(|w| t.contains(w));
        match self {
            Category::Chair => has(&["chair"]) && !has(&["wheelchair", "high", "ottoman", "sofa"]),
            Category::Sofa => has(&["sofa", "couch"]) && !has(&["opened"]),
            Category::Diningtable => {
                has(&["table"])
                    && (60.0..=80.0).contains(&piece.height_cm)
                    && !has(&["tablet", "tennis", "football", "pool", "fan", "glass", "bedside", "desk", "office_"])
            }
            _ => false,
        }
    }
}

/// The models of a category: the source domain's and the held-out `shape` domain's.
#[derive(Clone, Debug, Serialize)]
pub struct Catalogue {
    pub category: Category,
    pub source: Vec<String>,
    pub shape: Vec<String>,
    /// The furniture pieces behind the names (empty for cars and FlightGear models).
    #[serde(skip)]
    pieces: Vec<sweethome::Piece>,
}

impl Catalogue {
    /// Cars and FlightGear models are listed by hand; furniture is every piece of the libraries
    /// that `takes` accepts, sorted by name, every third one held out for `shape`.
    pub fn of(assets: &Assets, category: Category) -> Result<Self> {
        let names = |models: &[Model]| models.iter().map(|m| m.name().to_string()).collect();
        let mut pieces = Vec::new();
        let (source, shape) = match category {
            Category::Car => (strings(&SOURCE_CARS), strings(&SHAPE_CARS)),
            Category::Aeroplane => (names(&SOURCE_AEROPLANES), names(&SHAPE_AEROPLANES)),
            Category::Bus => (names(&SOURCE_BUSES), names(&SHAPE_BUSES)),
            _ => {
                pieces = furniture(assets)?.into_iter().filter(|p| category.takes(p)).collect();
                pieces.sort_by(|a, b| a.name.cmp(&b.name));
                pieces.dedup_by(|a, b| a.name == b.name);
                let (shape, source): (Vec<_>, Vec<_>) =
                    pieces.iter().map(|p| p.name.clone()).enumerate().partition(|(i, _)| i % 3 == 2);
                (source.into_iter().map(|(_, n)| n).collect(), shape.into_iter().map(|(_, n)| n).collect())
            }
        };
        if source.is_empty() || shape.is_empty() {
            bail!("no {} models found: run `make assets-all`", category.name());
        }
        Ok(Catalogue { category, source, shape, pieces })
    }

    /// Loads model `name` in the canonical frame, normalised: cars to length 1 (as always), the
    /// other categories to a largest extent of 1.
    pub fn load(&self, assets: &Assets, name: &str) -> Result<TexturedMesh> {
        let unknown = || format!("no {} model named {name}", self.category.name());
        let mut mesh = match self.category {
            Category::Car => return Ok(Car::load(assets, name)?.mesh),
            Category::Aeroplane | Category::Bus => {
                let (source, shape) = match self.category {
                    Category::Aeroplane => (&SOURCE_AEROPLANES[..], &SHAPE_AEROPLANES[..]),
                    _ => (&SOURCE_BUSES[..], &SHAPE_BUSES[..]),
                };
                let model = source.iter().chain(shape).find(|m| m.name() == name).with_context(unknown)?;
                let mut mesh = flightgear::load(assets, &assets.flightgear, model)?;
                to_canonical(&mut mesh, model.front.vector());
                mesh
            }
            _ => {
                let piece = self.pieces.iter().find(|p| p.name == name).with_context(unknown)?;
                let library = name.split('/').next().unwrap_or_default();
                let archive = assets.sweethome.join(format!("{library}.sh3f"));
                let mut mesh = sweethome::load(&archive, piece, &assets.cache)?;
                // Sweet Home 3D shows a piece from its front, looking down −z.
                to_canonical(&mut mesh, [0.0, 0.0, 1.0]);
                if self.category == Category::Diningtable {
                    long_side_to_front(&mut mesh);
                }
                mesh
            }
        };
        normalise(&mut mesh);
        Ok(mesh)
    }
}

fn strings(names: &[&str]) -> Vec<String> {
    names.iter().map(|s| s.to_string()).collect()
}

fn furniture(assets: &Assets) -> Result<Vec<sweethome::Piece>> {
    let mut all = Vec::new();
    for library in LIBRARIES {
        all.extend(sweethome::catalogue(&assets.sweethome.join(format!("{library}.sh3f")))?);
    }
    Ok(all)
}

/// From a y-up frame whose front points along `front` (horizontal) to the canonical one: y is
/// −front, z is up, x = y × z (the object's left).
fn to_canonical(mesh: &mut TexturedMesh, front: [f64; 3]) {
    let y = front.map(|c| -c);
    let z = [0.0, 1.0, 0.0];
    let x = [y[1] * z[2] - y[2] * z[1], y[2] * z[0] - y[0] * z[2], y[0] * z[1] - y[1] * z[0]];
    let dot = |a: [f64; 3], p: [f64; 3]| a[0] * p[0] + a[1] * p[1] + a[2] * p[2];
    mesh.map_positions(|p| [dot(x, p), dot(y, p), dot(z, p)]);
}

/// A table has no front of its own (the libraries orient them either way): its long axis is
/// put along x, so that the front (−y) is a long side, as a sofa's. What is left is a 180°
/// symmetry (all of it for round tops), which the error metric has to handle.
fn long_side_to_front(mesh: &mut TexturedMesh) {
    let (lo, hi) = mesh.bounds();
    if hi[1] - lo[1] > hi[0] - lo[0] {
        // A quarter turn about z: (x, y) → (−y, x).
        mesh.map_positions(|[x, y, z]| [-y, x, z]);
    }
}

/// Centres the mesh on its bounding box and scales its largest extent to 1.
fn normalise(mesh: &mut TexturedMesh) {
    let (lo, hi) = mesh.bounds();
    let centre: [f64; 3] = std::array::from_fn(|a| (lo[a] + hi[a]) / 2.0);
    let size = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    mesh.map_positions(|p| std::array::from_fn(|a| (p[a] - centre[a]) / size));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_frame_is_a_rotation() {
        // Sweet Home 3D: front +z, left +x (seen from the front, the viewer's right).
        let mut m = TexturedMesh { positions: vec![[1.0, 2.0, 3.0]], ..Default::default() };
        to_canonical(&mut m, [0.0, 0.0, 1.0]);
        assert_eq!(m.positions[0], [1.0, -3.0, 2.0]);
        // The TORCS car frame (front +x, right +z) gives the car loader's (−z, −x, y).
        let mut m = TexturedMesh { positions: vec![[1.0, 2.0, 3.0]], ..Default::default() };
        to_canonical(&mut m, [1.0, 0.0, 0.0]);
        assert_eq!(m.positions[0], [-3.0, -1.0, 2.0]);
    }

    #[test]
    fn only_dining_tables_repeat_themselves_about_the_up_axis() {
        use crate::loader::training_pose;
        use udapose_engine::Pose;
        for c in Category::ALL {
            assert_eq!(Category::from_name(c.name()), Some(c));
            assert_eq!(c.up_symmetry("Lib/a_model") == UpSymmetry::NONE, c != Category::Diningtable, "{c:?}");
        }
        let table = |m: &str| Category::Diningtable.up_symmetry(m);
        assert_eq!(table("Scopia/table4"), UpSymmetry::Order(2));
        assert_eq!(table("Scopia/round-table"), UpSymmetry::Order(4));
        assert_eq!(table("BlendSwap-CC-0/tableWithTablecloth"), UpSymmetry::Continuous);
        // Training sees one azimuth for the look-alikes; nothing else of the pose changes.
        let pose = Pose::new(3.0, 0.2, -0.1, 5.0);
        let turned = training_pose(pose, table("Scopia/table4"));
        assert!((turned.azimuth - (3.0 - std::f64::consts::PI)).abs() < 1e-12);
        assert_eq!((turned.elevation, turned.theta, turned.distance), (0.2, -0.1, 5.0));
        assert_eq!(training_pose(pose, Category::Car.up_symmetry("car1")), pose);
    }

    #[test]
    fn furniture_titles_follow_voc() {
        let piece = |title: &str, height_cm: f64| sweethome::Piece {
            name: format!("Lib/{}", title.replace(' ', "_")),
            title: title.into(),
            height_cm,
            ..Default::default()
        };
        assert!(Category::Chair.takes(&piece("Winchester armchair", 100.0)));
        assert!(!Category::Chair.takes(&piece("Wheelchair", 90.0)));
        assert!(Category::Sofa.takes(&piece("Futon couch", 88.0)));
        assert!(Category::Diningtable.takes(&piece("Oak table", 74.1)));
        assert!(!Category::Diningtable.takes(&piece("Table", 40.0)), "a low table is a coffee table");
        assert!(!Category::Diningtable.takes(&piece("Tablet", 0.8)));
        assert!(!Category::Sofa.takes(&piece("Table", 75.0)));
    }
}
