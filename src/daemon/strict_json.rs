//! JSON parsed strictly for the protocol: like `serde_json::from_slice::<Value>`, but a
//! duplicate key at any depth is an error naming the key and where it is (serde_json keeps
//! the last one, so `{"steps":3,"steps":3000}` would silently run 3000 frames).
//! serde_json's own recursion limit (128 levels) still bounds the nesting.

use serde::de::{DeserializeSeed, Deserializer, MapAccess, SeqAccess, Visitor};
use serde_json::{Map, Value};
use std::fmt;

/// Parse one JSON document, refusing duplicate keys. The error is serde_json's message
/// (with its line and column) or `duplicate key "k" in <path>`.
pub fn parse(bytes: &[u8]) -> Result<Value, serde_json::Error> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let v = Strict {
        path: String::new(),
    }
    .deserialize(&mut de)?;
    de.end()?;
    Ok(v)
}

/// A value at `path` (`""` at the top, `job`, `job.study[2]`, ...).
struct Strict {
    path: String,
}

impl Strict {
    fn child(&self, key: &str) -> Strict {
        let path = match self.path.is_empty() {
            true => key.to_string(),
            false => format!("{}.{key}", self.path),
        };
        Strict { path }
    }

    fn index(&self, i: usize) -> Strict {
        Strict {
            path: format!("{}[{i}]", self.path),
        }
    }

    fn where_(&self) -> String {
        match self.path.is_empty() {
            true => "the request".to_string(),
            false => format!("`{}`", self.path),
        }
    }
}

impl<'de> DeserializeSeed<'de> for Strict {
    type Value = Value;
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> Visitor<'de> for Strict {
    type Value = Value;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_bool<E>(self, v: bool) -> Result<Value, E> {
        Ok(Value::Bool(v))
    }
    fn visit_i64<E>(self, v: i64) -> Result<Value, E> {
        Ok(Value::from(v))
    }
    fn visit_u64<E>(self, v: u64) -> Result<Value, E> {
        Ok(Value::from(v))
    }
    fn visit_f64<E>(self, v: f64) -> Result<Value, E> {
        // serde_json never hands a non-finite number to a visitor.
        Ok(serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number))
    }
    fn visit_str<E>(self, v: &str) -> Result<Value, E> {
        Ok(Value::String(v.to_string()))
    }
    fn visit_string<E>(self, v: String) -> Result<Value, E> {
        Ok(Value::String(v))
    }
    fn visit_unit<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }
    fn visit_none<E>(self) -> Result<Value, E> {
        Ok(Value::Null)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Value, A::Error> {
        let mut v = Vec::new();
        while let Some(x) = seq.next_element_seed(self.index(v.len()))? {
            v.push(x);
        }
        Ok(Value::Array(v))
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Value, A::Error> {
        let mut m = Map::new();
        while let Some(key) = map.next_key::<String>()? {
            if m.contains_key(&key) {
                return Err(serde::de::Error::custom(format!(
                    "duplicate key {key:?} in {}",
                    self.where_()
                )));
            }
            let v = map.next_value_seed(self.child(&key))?;
            m.insert(key, v);
        }
        Ok(Value::Object(m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duplicates_are_named_at_any_depth_and_the_rest_parses_as_serde_json_does() {
        let e = parse(br#"{"kind":"list","kind":"hello"}"#).unwrap_err();
        assert!(
            e.to_string()
                .starts_with(r#"duplicate key "kind" in the request"#),
            "{e}"
        );
        let e = parse(br#"{"job":{"steps":3,"x":[{"a":1,"a":2}],"steps":9}}"#).unwrap_err();
        assert!(
            e.to_string()
                .starts_with(r#"duplicate key "a" in `job.x[0]`"#),
            "{e}"
        );
        let text = br#"{"a":[1,-2,3.5,"s",null,true,{"b":{}}],"c":18446744073709551615}"#;
        assert_eq!(
            parse(text).unwrap(),
            serde_json::from_slice::<Value>(text).unwrap()
        );
        assert!(parse(b"{} {}").is_err(), "trailing data");
        assert!(parse(&[b'['; 200]).is_err(), "recursion limit");
    }
}
