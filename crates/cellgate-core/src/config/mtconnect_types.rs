//! The MTConnect data item types a PLC tag may be (`[[plcs.tags]] mtconnect = { type, units }`),
//! with their category and the units their observations are in: kept with the configuration,
//! which checks them; the agent (`crate::mtconnect`) shows them. Only types whose Streams
//! element is the type's name in CamelCase (`ROTARY_VELOCITY` → `RotaryVelocity`), as the
//! MTConnect 2.5 schema has them; the units are the schema's `UnitsEnum`.

/// SAMPLE or EVENT: the category a tag's data item takes (MTConnect Part 2, "DataItem").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TagCategory {
    /// A measured value with units.
    Sample,
    /// A count, or a value without units.
    Event,
}

/// One type: its name, its category, and the units a SAMPLE reports in by default.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TagType {
    /// The standard's name (`TEMPERATURE`).
    pub name: &'static str,
    /// SAMPLE (a measured value with units) or EVENT (a count, a value without units).
    pub category: TagCategory,
    /// The units of a SAMPLE (the standard's for the type), `None` for an EVENT.
    pub units: Option<&'static str>,
}

const fn sample(name: &'static str, units: &'static str) -> TagType {
    TagType {
        name,
        category: TagCategory::Sample,
        units: Some(units),
    }
}

const fn event(name: &'static str) -> TagType {
    TagType {
        name,
        category: TagCategory::Event,
        units: None,
    }
}

/// The types a tag may be.
pub const TAG_TYPES: &[TagType] = &[
    event("VARIABLE"),
    event("PART_COUNT"),
    sample("ACCUMULATED_TIME", "SECOND"),
    sample("ANGLE", "DEGREE"),
    sample("CONCENTRATION", "PERCENT"),
    sample("DISPLACEMENT", "MILLIMETER"),
    sample("ELECTRICAL_ENERGY", "WATT_SECOND"),
    sample("FILL_LEVEL", "PERCENT"),
    sample("FLOW", "LITER/SECOND"),
    sample("FREQUENCY", "HERTZ"),
    sample("LENGTH", "MILLIMETER"),
    sample("LINEAR_FORCE", "NEWTON"),
    sample("LOAD", "PERCENT"),
    sample("MASS", "KILOGRAM"),
    sample("PATH_FEEDRATE", "MILLIMETER/SECOND"),
    sample("POSITION", "MILLIMETER"),
    sample("PRESSURE", "PASCAL"),
    sample("PROCESS_TIMER", "SECOND"),
    sample("RESISTANCE", "OHM"),
    sample("ROTARY_VELOCITY", "REVOLUTION/MINUTE"),
    sample("SOUND_LEVEL", "DECIBEL"),
    sample("TEMPERATURE", "CELSIUS"),
    sample("TORQUE", "NEWTON_METER"),
    sample("VELOCITY", "MILLIMETER/SECOND"),
    sample("VISCOSITY", "PASCAL_SECOND"),
    sample("VOLUME_FLUID", "MILLILITER"),
    sample("WATTAGE", "WATT"),
];

/// The schema's `UnitsEnum` (MTConnectDevices_2.5.xsd).
pub const UNITS: &[&str] = &[
    "AMPERE",
    "CELSIUS",
    "COUNT",
    "DECIBEL",
    "DEGREE",
    "DEGREE_3D",
    "DEGREE/SECOND",
    "DEGREE/SECOND^2",
    "HERTZ",
    "JOULE",
    "KILOGRAM",
    "LITER",
    "LITER/SECOND",
    "MICRO_RADIAN",
    "MILLIMETER",
    "MILLIMETER_3D",
    "MILLIMETER/REVOLUTION",
    "MILLIMETER/SECOND",
    "MILLIMETER/SECOND^2",
    "NEWTON",
    "NEWTON_METER",
    "OHM",
    "PASCAL",
    "PASCAL_SECOND",
    "PERCENT",
    "PH",
    "REVOLUTION/MINUTE",
    "SECOND",
    "SIEMENS/METER",
    "VOLT",
    "VOLT_AMPERE",
    "VOLT_AMPERE_REACTIVE",
    "WATT",
    "WATT_SECOND",
    "GRAM/CUBIC_METER",
    "CUBIC_MILLIMETER",
    "CUBIC_MILLIMETER/SECOND",
    "CUBIC_MILLIMETER/SECOND^2",
    "MILLIGRAM",
    "MILLIGRAM/CUBIC_MILLIMETER",
    "MILLILITER",
    "COUNT/SECOND",
    "PASCAL/SECOND",
    "UNIT_VECTOR_3D",
    "REVOLUTION/SECOND^2",
    "REVOLUTION/SECOND",
    "GRAM",
    "METER/SECOND^2",
    "COULOMB",
    "CUBIC_METER",
    "SQUARE_MILLIMETER",
];

/// The type named `name` (as the standard spells it), if a tag may be one.
pub fn tag_type(name: &str) -> Option<TagType> {
    TAG_TYPES.iter().copied().find(|t| t.name == name)
}

/// `units` as the schema spells it, if it is one of the schema's.
pub fn units(name: &str) -> Option<&'static str> {
    UNITS.iter().copied().find(|u| *u == name)
}
