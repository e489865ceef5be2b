//! Bone layers: the label stored per voxel and reported as the paper's "bone layer" feature.
//!
//! The numeric ids are part of the data format (datasets, protocol): never renumber them.

/// The tissue class of a voxel. `#[repr(u8)]`: the id is what volumes and records store.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Layer {
    /// Air, soft tissue, or bone that has been drilled away. Holds no drillable material.
    Outside = 0,
    /// Cortical (compact) bone.
    Cortical = 1,
    /// Cancellous (trabecular) bone.
    Cancellous = 2,
    /// Bone marrow in the medullary canal.
    Marrow = 3,
    /// Necrotic bone (a lesion: sclerotic rim around a lucent core).
    Necrosis = 4,
}

/// A layer is written as its id wherever it is serialised (the reports to Python, the wire).
impl serde::Serialize for Layer {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_u8(self.id())
    }
}

impl Layer {
    /// Every layer, in id order.
    pub const ALL: [Layer; 5] = [Layer::Outside, Layer::Cortical, Layer::Cancellous, Layer::Marrow, Layer::Necrosis];
    /// Number of layers (valid ids are `0..COUNT`).
    pub const COUNT: usize = 5;

    /// The layer with this id, if any.
    #[must_use]
    pub fn from_id(id: u8) -> Option<Layer> {
        Self::ALL.get(id as usize).copied()
    }

    /// The stable numeric id.
    #[must_use]
    pub fn id(self) -> u8 {
        self as u8
    }

    /// Lower-case name used in files, the CLI and Python.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Layer::Outside => "outside",
            Layer::Cortical => "cortical",
            Layer::Cancellous => "cancellous",
            Layer::Marrow => "marrow",
            Layer::Necrosis => "necrosis",
        }
    }

    /// Whether voxels of this layer hold drillable material.
    #[must_use]
    pub fn is_solid(self) -> bool {
        self != Layer::Outside
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_are_stable() {
        for layer in Layer::ALL {
            assert_eq!(Layer::from_id(layer.id()), Some(layer));
        }
        assert_eq!(Layer::Cortical.id(), 1);
        assert_eq!(Layer::Necrosis.id(), 4);
        assert_eq!(Layer::from_id(5), None);
        assert!(!Layer::Outside.is_solid());
        assert!(Layer::Marrow.is_solid());
    }
}
