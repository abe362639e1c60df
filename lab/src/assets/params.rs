//! TORCS parameter files (`<params>` XML: nested `<section name>` with `<attnum>` / `<attstr>`),
//! read with a small tag scanner: the files use no entities and we need no more than that.

use std::collections::HashMap;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ParamsError {
    #[error("malformed TORCS params: {0}")]
    Malformed(String),
    #[error("missing parameter {0}")]
    Missing(String),
    #[error("parameter {name}: unknown unit {unit:?}")]
    Unit { name: String, unit: String },
}

/// Values keyed by `section/sub/attribute`; numbers keep their unit until read.
#[derive(Debug, Default)]
pub struct Params {
    numbers: HashMap<String, (f64, String)>,
    strings: HashMap<String, String>,
}

impl Params {
    pub fn parse(xml: &str) -> Result<Self, ParamsError> {
        let mut params = Params::default();
        let mut path: Vec<String> = Vec::new();
        let mut rest = xml;
        while let Some(start) = rest.find('<') {
            rest = &rest[start..];
            if let Some(after) = rest.strip_prefix("<!--") {
                let end = after.find("-->").ok_or_else(|| ParamsError::Malformed("unclosed comment".into()))?;
                rest = &after[end + 3..];
                continue;
            }
            let end = rest.find('>').ok_or_else(|| ParamsError::Malformed("unclosed tag".into()))?;
            let tag = &rest[1..end];
            rest = &rest[end + 1..];
            params.tag(tag, &mut path)?;
        }
        Ok(params)
    }

    fn tag(&mut self, tag: &str, path: &mut Vec<String>) -> Result<(), ParamsError> {
        let name = tag.split_whitespace().next().unwrap_or("");
        let key = |path: &[String], attr: &str| {
            let mut k = path.join("/");
            k.push('/');
            k.push_str(attr);
            k
        };
        match name {
            "section" => path.push(attribute(tag, "name").unwrap_or_default()),
            "/section" => {
                path.pop().ok_or_else(|| ParamsError::Malformed("unbalanced </section>".into()))?;
            }
            "attnum" => {
                let attr = attribute(tag, "name")
                    .ok_or_else(|| ParamsError::Malformed(format!("attnum without name: {tag}")))?;
                let k = key(path, &attr);
                let val = attribute(tag, "val").and_then(|v| v.trim().parse::<f64>().ok());
                let val = val.ok_or_else(|| ParamsError::Malformed(format!("{k}: bad value")))?;
                self.numbers.insert(k, (val, attribute(tag, "unit").unwrap_or_default()));
            }
            "attstr" => {
                let attr = attribute(tag, "name")
                    .ok_or_else(|| ParamsError::Malformed(format!("attstr without name: {tag}")))?;
                self.strings.insert(key(path, &attr), attribute(tag, "val").unwrap_or_default());
            }
            _ => {}
        }
        Ok(())
    }

    /// A length in metres.
    pub fn length(&self, key: &str) -> Result<f64, ParamsError> {
        let (val, unit) = self.numbers.get(key).ok_or_else(|| ParamsError::Missing(key.into()))?;
        Ok(val * length_scale(key, unit)?)
    }

    /// A dimensionless number (no unit given).
    pub fn ratio(&self, key: &str) -> Result<f64, ParamsError> {
        match self.numbers.get(key) {
            Some((val, unit)) if unit.is_empty() => Ok(*val),
            Some((_, unit)) => Err(ParamsError::Unit { name: key.into(), unit: unit.clone() }),
            None => Err(ParamsError::Missing(key.into())),
        }
    }

    pub fn string(&self, key: &str) -> Option<&str> {
        self.strings.get(key).map(String::as_str)
    }
}

fn attribute(tag: &str, name: &str) -> Option<String> {
    let needle = format!("{name}=\"");
    let mut search = tag;
    loop {
        let at = search.find(&needle)?;
        // Match whole attribute names only ("val" must not match "interval").
        let boundary = at == 0 || search.as_bytes()[at - 1].is_ascii_whitespace();
        let value = &search[at + needle.len()..];
        if boundary {
            return value.find('"').map(|end| value[..end].to_string());
        }
        search = value;
    }
}

/// Metres per `unit`; TORCS writes lengths without a unit in metres.
fn length_scale(key: &str, unit: &str) -> Result<f64, ParamsError> {
    Ok(match unit {
        "" | "m" => 1.0,
        "cm" => 0.01,
        "mm" => 0.001,
        "in" => 0.0254,
        "ft" => 0.3048,
        other => return Err(ParamsError::Unit { name: key.into(), unit: other.into() }),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sections_units_and_strings() {
        let xml = r#"<?xml version="1.0"?>
            <!-- <section name="commented"> -->
            <!DOCTYPE params SYSTEM "params.dtd">
            <params name="car">
              <section name="Front Axle"><attnum name="xpos" min="0.5" max="2.5" val="1.22"/></section>
              <section name="Front Left Wheel">
                <attnum name="rim diameter" unit="in" val="18.0"/>
                <attnum name="tire width" unit="mm" val="255"/>
                <attnum name="tire height-width ratio" val=".40"/>
              </section>
              <section name="Graphic Objects"><attstr name="3d wheel directory" in="a,b" val="trb1-5"/></section>
            </params>"#;
        let p = Params::parse(xml).unwrap();
        assert_eq!(p.length("Front Axle/xpos").unwrap(), 1.22);
        assert!((p.length("Front Left Wheel/rim diameter").unwrap() - 0.4572).abs() < 1e-12);
        assert!((p.length("Front Left Wheel/tire width").unwrap() - 0.255).abs() < 1e-12);
        assert_eq!(p.ratio("Front Left Wheel/tire height-width ratio").unwrap(), 0.4);
        assert!(p.ratio("Front Left Wheel/tire width").is_err(), "a length is not a ratio");
        assert_eq!(p.string("Graphic Objects/3d wheel directory"), Some("trb1-5"));
        assert!(matches!(p.length("Rear Axle/xpos"), Err(ParamsError::Missing(_))));
        assert!(Params::parse("<section name=\"a\"></section></section>").is_err());
        let odd = Params::parse("<attnum name=\"x\" unit=\"furlong\" val=\"1\"/>").unwrap();
        assert!(matches!(odd.length("/x"), Err(ParamsError::Unit { .. })));
    }
}
