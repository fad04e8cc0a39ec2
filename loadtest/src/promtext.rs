//! Reads the server's Prometheus `/metrics` counters, to compare the server's counts with
//! the load generator's own.
use std::collections::BTreeMap;
use std::time::Duration;

/// One sample: metric name, labels, value.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    pub name: String,
    pub labels: BTreeMap<String, String>,
    pub value: f64,
}

/// Parses the Prometheus text exposition format (comments and malformed lines are skipped).
pub fn parse(text: &str) -> Vec<Sample> {
    text.lines().filter_map(parse_line).collect()
}

fn parse_line(line: &str) -> Option<Sample> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return None;
    }
    let (name, labels, rest) = match line.find('{') {
        Some(open) => {
            let close = line.rfind('}')?;
            (
                &line[..open],
                parse_labels(&line[open + 1..close])?,
                &line[close + 1..],
            )
        }
        None => {
            let sp = line.find(' ')?;
            (&line[..sp], BTreeMap::new(), &line[sp..])
        }
    };
    let value = rest.split_whitespace().next()?.parse().ok()?;
    Some(Sample {
        name: name.to_string(),
        labels,
        value,
    })
}

fn parse_labels(s: &str) -> Option<BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        let eq = rest.find('=')?;
        let key = rest[..eq].trim().to_string();
        let after = rest[eq + 1..].strip_prefix('"')?;
        let mut val = String::new();
        let mut chars = after.char_indices();
        let end = loop {
            let (i, c) = chars.next()?;
            match c {
                '\\' => {
                    let (_, n) = chars.next()?;
                    val.push(if n == 'n' { '\n' } else { n });
                }
                '"' => break i,
                c => val.push(c),
            }
        };
        out.insert(key, val);
        rest = after[end + 1..]
            .trim_start()
            .trim_start_matches(',')
            .trim_start();
    }
    Some(out)
}

/// Sum of `name` over samples whose `label` is one of `values` (all samples when `label` is
/// `None`), with extra label filters `also`.
pub fn sum(
    samples: &[Sample],
    name: &str,
    label: Option<(&str, &[String])>,
    also: &[(&str, &str)],
) -> f64 {
    samples
        .iter()
        .filter(|s| s.name == name)
        .filter(|s| label.is_none_or(|(k, vs)| s.labels.get(k).is_some_and(|v| vs.contains(v))))
        .filter(|s| {
            also.iter()
                .all(|(k, v)| s.labels.get(*k).is_some_and(|x| x == v))
        })
        .map(|s| s.value)
        .sum()
}

/// Fetches and parses `GET {base}/metrics`.
pub async fn scrape(base: &str) -> anyhow::Result<Vec<Sample>> {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(5))
        .build()?;
    let url = format!("{}/metrics", base.trim_end_matches('/'));
    let resp = client.get(&url).send().await?.error_for_status()?;
    Ok(parse(&resp.text().await?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_counters_with_labels() {
        let text = "# TYPE crossview_batches_total counter\n\
            crossview_batches_total{scene=\"a\"} 12\n\
            crossview_batches_total{scene=\"b\"} 3\n\
            crossview_frames_total{scene=\"a\",state=\"complete\"} 4\n\
            crossview_frames_total{scene=\"a\",state=\"partial\"} 1\n\
            up 1\n\
            weird{x=\"q\\\"uote\"} 2.5\n";
        let s = parse(text);
        assert_eq!(s.len(), 6);
        let a = vec!["a".to_string()];
        assert_eq!(
            sum(&s, "crossview_batches_total", Some(("scene", &a)), &[]),
            12.0
        );
        assert_eq!(sum(&s, "crossview_batches_total", None, &[]), 15.0);
        assert_eq!(
            sum(
                &s,
                "crossview_frames_total",
                Some(("scene", &a)),
                &[("state", "partial")]
            ),
            1.0
        );
        assert_eq!(s[5].labels["x"], "q\"uote");
    }
}
