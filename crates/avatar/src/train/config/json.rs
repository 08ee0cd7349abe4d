//! Config files and overrides: a file's keys merged over the preset it names, `--set` values
//! over a configuration, both by the keys of the whole configuration, so a misspelt key is an
//! error naming it rather than a silently ignored value.

use std::path::Path;

use serde_json::Value;

use super::TrainConfig;
use crate::AvatarError;

impl TrainConfig {
    /// Reads a JSON config file: its keys over the preset it names. A key the configuration
    /// does not have is an error naming it.
    pub fn from_file(path: &Path) -> Result<Self, AvatarError> {
        let text = std::fs::read_to_string(path).map_err(|e| AvatarError::file(path, e))?;
        let value: Value = serde_json::from_str(&text)
            .map_err(|e| AvatarError::file(path, format!("not valid JSON: {e}")))?;
        let preset = value
            .get("preset")
            .and_then(Value::as_str)
            .unwrap_or("cpu")
            .to_string();
        let preset = Self::preset(&preset).map_err(|e| AvatarError::file(path, e))?;
        let mut base = serde_json::to_value(preset).expect("serialisable");
        if let Some(key) = unknown_key(&base, &value, "") {
            return Err(AvatarError::file(
                path,
                format!("unknown configuration key `{key}`"),
            ));
        }
        merge(&mut base, &value);
        let config: Self = serde_json::from_value(base)
            .map_err(|e| AvatarError::file(path, format!("bad configuration: {e}")))?;
        config.validate().map_err(|e| AvatarError::file(path, e))?;
        Ok(config)
    }

    /// Applies `key=value` overrides (dotted keys, JSON values; bare words are strings).
    pub fn with_overrides(self, overrides: &[String]) -> Result<Self, AvatarError> {
        let mut value = serde_json::to_value(&self).expect("serialisable");
        for item in overrides {
            let (key, text) = item.split_once('=').ok_or_else(|| {
                AvatarError::config(item, "expected key=value, e.g. steps.joint=500")
            })?;
            let parsed: Value =
                serde_json::from_str(text).unwrap_or_else(|_| Value::String(text.to_string()));
            let mut slot = &mut value;
            for part in key.split('.') {
                slot = slot
                    .as_object_mut()
                    .and_then(|o| o.get_mut(part))
                    .ok_or_else(|| AvatarError::config(key, "no such key"))?;
            }
            *slot = parsed;
        }
        let config: Self = serde_json::from_value(value)
            .map_err(|e| AvatarError::config("--set", format!("{e}")))?;
        config.validate()?;
        Ok(config)
    }
}

/// The first key of `patch` (as a dotted path) that `base`, a whole configuration, lacks.
fn unknown_key(base: &Value, patch: &Value, prefix: &str) -> Option<String> {
    let (Value::Object(b), Value::Object(p)) = (base, patch) else {
        return None;
    };
    p.iter().find_map(|(k, v)| {
        let path = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match b.get(k) {
            None => Some(path),
            Some(inner) => unknown_key(inner, v, &path),
        }
    })
}

/// Deep merge of JSON objects: `patch` wins.
fn merge(base: &mut Value, patch: &Value) {
    match (base, patch) {
        (Value::Object(b), Value::Object(p)) => {
            for (k, v) in p {
                match b.get_mut(k) {
                    Some(slot) if slot.is_object() && v.is_object() => merge(slot, v),
                    _ => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, p) => *b = p.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use f3g_nets::LpipsNet;

    #[test]
    fn files_merge_over_the_preset_and_reject_unknown_keys_and_bad_values() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.json");
        std::fs::write(&path, r#"{"steps": {"joint": 7}, "lr": 0.002}"#).unwrap();
        let c = TrainConfig::from_file(&path).unwrap();
        let preset = TrainConfig::cpu().steps.body;
        assert_eq!((c.steps.joint, c.lr, c.steps.body), (7, 0.002, preset));
        std::fs::write(&path, r#"{"map_resolution": 1073741824}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("map_resolution"), "{e}");
        std::fs::write(&path, r#"{"stepz": 3}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("c.json") && e.contains("stepz"), "{e}");
        std::fs::write(&path, r#"{"steps": {"joint": 7, "warp": 1}}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("warp"), "{e}");
        std::fs::write(&path, r#"{"body_scale": 3}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("body_scale"), "{e}");
        std::fs::write(&path, r#"{"map_resolution": 100}"#).unwrap();
        let e = TrainConfig::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("map_resolution"), "{e}");
    }

    #[test]
    fn overrides_use_dotted_keys() {
        let c = TrainConfig::cpu()
            .with_overrides(&["steps.joint=3".into(), "lpips_net=vgg".into()])
            .unwrap();
        assert_eq!((c.steps.joint, c.lpips_net), (3, LpipsNet::Vgg));
        let e = TrainConfig::cpu()
            .with_overrides(&["steps.nope=3".into()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("steps.nope"), "{e}");
        assert!(
            TrainConfig::cpu()
                .with_overrides(&["lr=-1".into()])
                .unwrap_err()
                .to_string()
                .contains("`lr`")
        );
    }
}
