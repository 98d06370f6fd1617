//! Refuses payloads that carry fields their schema does not have, as the Python
//! runner's `check_fields` does (protobuf keeps unknown fields; prost drops them
//! silently, so another message's bytes would pass for a request).
//!
//! The schemas come from the descriptor set build.rs embeds, so every message of
//! `proto/` is checked by the same code, nested messages included.

use std::collections::HashMap;
use std::sync::OnceLock;

use prost::Message;
use prost_types::field_descriptor_proto::{Label, Type};
use prost_types::FileDescriptorSet;

/// A field as the wire may carry it: the wire types it may come as, and the message
/// type of a nested message field.
#[derive(Clone, Debug)]
struct Field {
    wire_types: Vec<u8>,
    message: Option<String>,
}

type Schemas = HashMap<String, HashMap<u32, Field>>;

fn schemas() -> &'static Schemas {
    static SCHEMAS: OnceLock<Schemas> = OnceLock::new();
    SCHEMAS.get_or_init(|| {
        let fds = FileDescriptorSet::decode(&include_bytes!(concat!(env!("OUT_DIR"), "/descriptors.bin"))[..])
            .expect("embedded descriptor set");
        let mut out = Schemas::new();
        for file in &fds.file {
            let package = file.package();
            for msg in &file.message_type {
                let mut fields = HashMap::new();
                for f in &msg.field {
                    let scalar = match f.r#type() {
                        Type::Double | Type::Fixed64 | Type::Sfixed64 => 1,
                        Type::Float | Type::Fixed32 | Type::Sfixed32 => 5,
                        Type::String | Type::Bytes | Type::Message | Type::Group => 2,
                        _ => 0, // varints: ints, bools, enums
                    };
                    let mut wire_types = vec![scalar];
                    if f.label() == Label::Repeated && scalar != 2 {
                        wire_types.push(2); // packed
                    }
                    let message =
                        (f.r#type() == Type::Message).then(|| f.type_name().trim_start_matches('.').to_string());
                    fields.insert(f.number() as u32, Field { wire_types, message });
                }
                out.insert(format!("{package}.{}", msg.name()), fields);
            }
        }
        out
    })
}

fn varint(buf: &mut &[u8]) -> Option<u64> {
    let mut value = 0u64;
    for shift in (0..64).step_by(7) {
        let (&byte, rest) = buf.split_first()?;
        *buf = rest;
        value |= u64::from(byte & 0x7f) << shift;
        if byte & 0x80 == 0 {
            return Some(value);
        }
    }
    None
}

/// The path of the first (sub)message of `data` (a `schema`, such as
/// `swarmrec.v1.VerifyRequest`) that holds a field its schema lacks; None when every
/// field is known. Call it on bytes that decoded: malformed bytes are reported here
/// as unknown too.
pub fn unknown_field(schema: &str, data: &[u8]) -> Option<String> {
    let fields = schemas().get(schema)?;
    let mut buf = data;
    let mut seen: HashMap<u32, usize> = HashMap::new();
    while !buf.is_empty() {
        let Some(tag) = varint(&mut buf) else {
            return Some(schema.to_string());
        };
        let (number, wire) = ((tag >> 3) as u32, (tag & 7) as u8);
        let field = match fields.get(&number) {
            Some(f) if f.wire_types.contains(&wire) => f,
            _ => return Some(schema.to_string()),
        };
        match wire {
            0 => {
                varint(&mut buf)?;
            }
            1 | 5 => {
                let n = if wire == 1 { 8 } else { 4 };
                if buf.len() < n {
                    return Some(schema.to_string());
                }
                buf = &buf[n..];
            }
            2 => {
                let Some(len) = varint(&mut buf) else {
                    return Some(schema.to_string());
                };
                let len = usize::try_from(len).ok().filter(|&l| l <= buf.len());
                let Some(len) = len else {
                    return Some(schema.to_string());
                };
                let (body, rest) = buf.split_at(len);
                buf = rest;
                if let Some(sub) = &field.message {
                    let i = seen.entry(number).or_insert(0);
                    if let Some(path) = unknown_field(sub, body) {
                        let name = sub.rsplit('.').next().unwrap_or(sub);
                        return Some(format!("{schema}.{name}[{i}]: {path}"));
                    }
                    *i += 1;
                }
            }
            _ => return Some(schema.to_string()),
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pb;

    #[test]
    fn a_message_of_its_own_schema_passes_and_another_ones_bytes_do_not() {
        let req = pb::VerifyRequest {
            query_id: 7,
            query: Some(pb::Constellation {
                robot_id: Some(1),
                frame_index: Some(2),
                labels: vec![1, 2, 3],
                positions_mm: vec![1, -2, 3, 4, 5, 6, 7, 8, 9],
                ..Default::default()
            }),
            candidate_frame_indices: vec![1, 2],
            distance_threshold_m: Some(0.5),
            ..Default::default()
        };
        assert_eq!(unknown_field("swarmrec.v1.VerifyRequest", &req.encode_to_vec()), None);
        let other = pb::ErrorReply {
            code: 2,
            message: "x".into(),
        };
        assert!(unknown_field("swarmrec.v1.VerifyRequest", &other.encode_to_vec()).is_some());
    }

    #[test]
    fn an_unknown_field_inside_a_nested_message_is_found() {
        // VerifyRequest.query (field 2) holding a field 9 (varint 1).
        let data = [0x12, 0x02, 0x48, 0x01];
        let found = unknown_field("swarmrec.v1.VerifyRequest", &data).expect("found");
        assert!(found.contains("Constellation"), "{found}");
    }
}
