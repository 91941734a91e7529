//! The protocol's JSON Schema (`docs/protocol.schema.json`, `rigctl schema`), derived with
//! schemars from the very types `daemon::protocol` serialises: a request line, and a line
//! the server writes (a reply or an event), with a definition for every type they carry.
//!
//! What serde does not say is added here: a request line's `v` and `id` (taken off by
//! `decode_request` before the request is decoded) and the protocol version the replies and
//! events carry. `tests/suite/protocol_schema.rs` holds the committed file to what this generates
//! and validates a real daemon's traffic against it.

use crate::daemon::protocol::{Request, ServerLine, MAX_ID, PROTOCOL_VERSION};
use schemars::generate::SchemaSettings;
use schemars::{json_schema, JsonSchema, Schema, SchemaGenerator};
use serde_json::{Map, Value};

/// One line of the rigd protocol (version 1), either way: a request a client writes, or a
/// reply or event the daemon writes. Clients must ignore fields and event kinds they do not
/// know; the daemon refuses requests with unknown fields or kinds (docs/protocol.md).
#[derive(JsonSchema)]
#[schemars(title = "rigd protocol 1", untagged)]
#[allow(dead_code)] // only its schema is used
enum Line {
    Request(Request),
    Server(ServerLine),
}

/// The schema document, keys sorted (the same text whatever map order serde_json builds with).
pub fn document() -> Value {
    let schema = SchemaSettings::draft2020_12()
        .into_generator()
        .into_root_schema_for::<Line>();
    sorted(schema.to_value())
}

/// The document as `docs/protocol.schema.json` holds it: pretty, ending in a newline.
pub fn document_text() -> String {
    let mut text = serde_json::to_string_pretty(&document()).expect("a schema is plain JSON");
    text.push('\n');
    text
}

fn sorted(v: Value) -> Value {
    match v {
        Value::Object(map) => {
            let mut entries: Vec<(String, Value)> = map.into_iter().collect();
            entries.sort_by(|a, b| a.0.cmp(&b.0));
            Value::Object(entries.into_iter().map(|(k, v)| (k, sorted(v))).collect())
        }
        Value::Array(items) => Value::Array(items.into_iter().map(sorted).collect()),
        other => other,
    }
}

/// The protocol version field: `1`.
pub fn version(_: &mut SchemaGenerator) -> Schema {
    json_schema!({
        "description": "The protocol version.",
        "type": "integer",
        "const": PROTOCOL_VERSION,
    })
}

/// A request's `id`, echoed exactly in its reply: a string, or an integer JSON readers all
/// hold exactly.
pub fn id(_: &mut SchemaGenerator) -> Schema {
    json_schema!({
        "description": "A string, or an integer within ±(2^53 - 1), echoed exactly.",
        "type": ["string", "integer"],
        "minimum": -(MAX_ID as i64),
        "maximum": MAX_ID,
    })
}

/// Every request variant also takes the line's `v` and `id` (`#[schemars(transform)]` on
/// `Request`): serde's `deny_unknown_fields` makes each variant closed, and the envelope
/// fields are the line's, not the request's.
pub fn request_envelope(schema: &mut Schema) {
    let mut gen = SchemaGenerator::default();
    let envelope = [("v", version(&mut gen)), ("id", id(&mut gen))];
    let Some(Value::Array(variants)) = schema.get_mut("oneOf") else {
        return;
    };
    for variant in variants {
        let Some(props) = variant.get_mut("properties").and_then(Value::as_object_mut) else {
            continue;
        };
        for (name, s) in &envelope {
            props.insert(name.to_string(), s.clone().to_value());
        }
    }
}

/// The values of the tag `tag` (`kind`, `event`) over a tagged enum's variants, as its
/// schema lists them.
pub fn tag_values(schema: &Value, tag: &str) -> Vec<String> {
    let empty = Vec::new();
    let variants = schema["oneOf"].as_array().unwrap_or(&empty);
    variants
        .iter()
        .filter_map(|v| v["properties"][tag]["const"].as_str())
        .map(str::to_string)
        .collect()
}

/// A schema for one of the document's definitions (`Request`, `ServerLine`, `HelloReply`
/// ...), with every definition beside it so its references resolve.
pub fn definition(doc: &Value, name: &str) -> Option<Value> {
    doc["$defs"].get(name)?;
    let mut s = Map::new();
    s.insert("$schema".into(), doc["$schema"].clone());
    s.insert("$defs".into(), doc["$defs"].clone());
    s.insert("$ref".into(), Value::String(format!("#/$defs/{name}")));
    Some(Value::Object(s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::protocol::{EventBody, EVENT_KINDS, REQUEST_KINDS};
    use std::collections::BTreeSet;

    /// The variants' tags as the schema has them against a capabilities list, with what to do.
    fn check(list: &[&str], schema: Value, tag: &str, what: &str) {
        let variants: BTreeSet<String> = tag_values(&schema, tag).into_iter().collect();
        let listed: BTreeSet<String> = list.iter().map(|k| k.to_string()).collect();
        assert!(variants.len() > 2, "no {tag} values in {schema}");
        if let Some(k) = variants.difference(&listed).next() {
            panic!("{what} `{k}` is missing from its capabilities list: add it to the list next to the enum in src/daemon/protocol.rs, so `hello` announces it");
        }
        if let Some(k) = listed.difference(&variants).next() {
            panic!("the capabilities list names `{k}`, which is not a {what}: remove it");
        }
        assert_eq!(list.len(), listed.len(), "a kind is listed twice: {list:?}");
    }

    #[test]
    fn the_capabilities_list_every_request_and_event_kind() {
        let gen = || SchemaSettings::draft2020_12().into_generator();
        let requests = gen().into_root_schema_for::<Request>().to_value();
        check(REQUEST_KINDS, requests, "kind", "request kind (Request)");
        let events = gen().into_root_schema_for::<EventBody>().to_value();
        check(EVENT_KINDS, events, "event", "event kind (EventBody)");
    }

    #[test]
    fn request_variants_take_the_envelope_and_nothing_else() {
        let doc = document();
        let req = &doc["$defs"]["Request"];
        let hello = req["oneOf"]
            .as_array()
            .unwrap()
            .iter()
            .find(|v| v["properties"]["kind"]["const"] == "hello")
            .expect("a hello variant");
        let props: BTreeSet<&str> = hello["properties"]
            .as_object()
            .unwrap()
            .keys()
            .map(String::as_str)
            .collect();
        assert_eq!(props, BTreeSet::from(["id", "kind", "v"]));
        assert_eq!(hello["additionalProperties"], false);
        assert_eq!(hello["properties"]["v"]["const"], 1);
        // The document's top: a line either way.
        assert_eq!(
            doc["anyOf"].as_array().map(Vec::len),
            Some(2),
            "{}",
            doc["anyOf"]
        );
        assert!(definition(&doc, "HelloReply").is_some());
        assert!(definition(&doc, "NoSuchType").is_none());
    }
}
