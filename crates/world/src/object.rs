//! The six objects and their fixed, non-switchable properties.

use serde::{Deserialize, Serialize};

use crate::Error;

/// One of the six objects of the paper.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ObjectKind {
    /// A 0.9 m cotton rope (radius 8 mm) grasped at one end: dragged across the table, lifted,
    /// lowered.
    Rope,
    /// An A4 sheet of 80 g/m² paper held at the middle of its top edge and waved in the air.
    Paper,
    /// A 0.45 m × 0.30 m cloth flag on a rigid stick (its top edge) held and waved.
    Flag,
    /// A plush sloth: volumetric body and head with four long soft limbs, lifted by its back and
    /// swung.
    Sloth,
    /// A feather duster: a stiff 0.38 m stem with a head of soft feather strands, waved.
    Duster,
    /// A sitting teddy bear, stiffer than the sloth, poked by a spherical finger (non-prehensile).
    Teddy,
}

impl ObjectKind {
    /// All six, in the paper's order.
    pub const ALL: [ObjectKind; 6] = [
        ObjectKind::Rope,
        ObjectKind::Paper,
        ObjectKind::Flag,
        ObjectKind::Sloth,
        ObjectKind::Duster,
        ObjectKind::Teddy,
    ];

    /// The object's name as used on the command line and in `dataset.json`.
    pub fn name(self) -> &'static str {
        match self {
            ObjectKind::Rope => "rope",
            ObjectKind::Paper => "paper",
            ObjectKind::Flag => "flag",
            ObjectKind::Sloth => "sloth",
            ObjectKind::Duster => "duster",
            ObjectKind::Teddy => "teddy",
        }
    }

    /// Whether the gripper pokes the object (a pushing sphere) instead of grasping it.
    pub fn is_push(self) -> bool {
        self == ObjectKind::Teddy
    }

    /// Whether the object is a solid whose tracked points lie on its surface.
    pub fn is_volumetric(self) -> bool {
        matches!(self, ObjectKind::Sloth | ObjectKind::Teddy)
    }
}

impl std::fmt::Display for ObjectKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for ObjectKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        ObjectKind::ALL
            .into_iter()
            .find(|o| o.name() == s)
            .ok_or_else(|| Error::UnknownObject(s.to_string()))
    }
}
