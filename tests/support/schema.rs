//! The protocol's JSON Schema as the tests check lines against it: a closed copy (no
//! property a definition does not describe) and validators of its definitions.

use rigd::daemon::schema::definition;
use serde_json::Value;
use std::collections::BTreeSet;

/// `doc` with every object closed where that is sound: `unevaluatedProperties: false` on
/// each definition, but those a `$ref` completes with its own properties (internally
/// tagged newtype variants: `Reply` and `Event` under `ServerLine`), which the referrer's
/// closing covers.
pub fn closed(doc: &Value) -> Value {
    fn completed(v: &Value, out: &mut BTreeSet<String>) {
        match v {
            Value::Object(m) => {
                if let (Some(Value::String(r)), true) =
                    (m.get("$ref"), m.contains_key("properties"))
                {
                    out.insert(r.trim_start_matches("#/$defs/").to_string());
                }
                m.values().for_each(|x| completed(x, out));
            }
            Value::Array(a) => a.iter().for_each(|x| completed(x, out)),
            _ => {}
        }
    }
    let mut skip = BTreeSet::new();
    completed(doc, &mut skip);
    assert!(skip.contains("Event") && skip.contains("Reply"), "{skip:?}");
    let mut doc = doc.clone();
    for (name, def) in doc["$defs"].as_object_mut().unwrap() {
        if !skip.contains(name) {
            def["unevaluatedProperties"] = false.into();
        }
    }
    doc
}

/// A validator of definition `name` of `doc`.
pub fn validator(doc: &Value, name: &str) -> jsonschema::Validator {
    let s = definition(doc, name).unwrap_or_else(|| panic!("no `{name}` in the schema"));
    jsonschema::draft202012::new(&s).unwrap_or_else(|e| panic!("schema `{name}`: {e}"))
}

/// What `v` finds wrong with `instance`, each with where.
pub fn errors(v: &jsonschema::Validator, instance: &Value) -> Vec<String> {
    v.iter_errors(instance)
        .map(|e| format!("{e} at {}", e.instance_path()))
        .collect()
}
