//! The dashboard's HTML: the task list and one task's pool, each a whole page whose
//! inline script polls its fragment (the same HTML without the page around it) and
//! swaps it in, so the page refreshes without a reload. No build step, nothing fetched
//! from elsewhere.

use std::fmt::Write;

use super::svg::{pool_svg, PALETTE};
use crate::core::{Pool, TaskConfig};
use crate::registry::TaskStats;

/// Text for HTML (element content or a quoted attribute).
pub(super) fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A query value, percent-encoded.
pub(super) fn encode(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            out.push(b as char);
        } else {
            let _ = write!(out, "%{b:02X}");
        }
    }
    out
}

const STYLE: &str = "body{font:14px system-ui,sans-serif;margin:1.5em;color:#222}\
table{border-collapse:collapse}td,th{padding:.25em .7em;border-bottom:1px solid #ddd;text-align:left}\
td.n{text-align:right;font-variant-numeric:tabular-nums}svg.pool text{font:11px sans-serif;fill:#555}\
rect.score{fill:#2c7fb8}rect.length{fill:#999}polyline{fill:none;stroke-width:1}\
.legend span{display:inline-block;width:.9em;height:.9em;margin:0 .2em 0 .8em;vertical-align:middle}\
.muted{color:#777}";

/// A whole page: `fragment` inside a container the script refreshes from `src` every
/// two seconds (with the page's `key`, if it has one).
pub(super) fn page(title: &str, src: &str, fragment: &str) -> String {
    let mut style = String::from(STYLE);
    for (i, [r, g, b]) in PALETTE.iter().enumerate() {
        let _ = write!(style, "polyline.d{i}{{stroke:#{r:02x}{g:02x}{b:02x}}}");
    }
    format!(
        r#"<!doctype html><html lang="en"><head><meta charset="utf-8"><title>{title}</title><style>{style}</style></head><body><div id="live" data-src="{src}">{fragment}</div><script>
const live = document.getElementById("live");
const key = new URLSearchParams(location.search).get("key");
async function refresh() {{
  const url = new URL(live.dataset.src, location.href);
  if (key) url.searchParams.set("key", key);
  try {{
    const r = await fetch(url, {{ cache: "no-store" }});
    if (r.ok) live.innerHTML = await r.text();
  }} catch (e) {{}}
}}
setInterval(refresh, 2000);
</script></body></html>"#,
        title = escape(title),
        src = escape(src),
    )
}

fn actions(c: &TaskConfig) -> String {
    match c.action_space.action_dim() {
        0 => format!("discrete {}", c.action_space.num_actions()),
        m => format!("continuous {m}"),
    }
}

fn config_text(c: &TaskConfig) -> String {
    format!(
        "capacity {}, k {}, start_step {}, min_pool_size {}, α {}, β {}, γ {}, max_len {}{}{}",
        c.pool_capacity,
        c.k,
        c.start_step,
        c.min_pool_size,
        c.alpha,
        c.beta,
        c.gamma,
        c.max_trajectory_len,
        if c.gate_potential {
            ", gate_potential"
        } else {
            ""
        },
        if c.require_score_spread {
            ", require_score_spread"
        } else {
            ""
        },
    )
}

fn score(x: f64, empty: bool) -> String {
    if empty {
        "–".into()
    } else {
        x.to_string()
    }
}

/// The task list fragment: a row per task, linking to its pool (with `key_query`, e.g.
/// `&key=…`, appended).
pub(super) fn tasks_fragment(tasks: &[(String, TaskConfig, TaskStats)], key_query: &str) -> String {
    let mut out = String::from("<h1>Tasks</h1>");
    if tasks.is_empty() {
        out.push_str(r#"<p class="muted">No tasks.</p>"#);
        return out;
    }
    out.push_str("<table class=\"tasks\"><tr><th>task</th><th>actions</th><th>config</th><th>pool</th><th>best</th><th>worst</th><th>version</th><th>episodes</th><th>steps</th></tr>");
    for (id, c, s) in tasks {
        let empty = s.pool_size == 0;
        let _ = write!(
            out,
            r#"<tr class="task" data-task="{eid}"><td><a href="/task?id={qid}{key_query}">{eid}</a></td><td>{}</td><td class="muted">{}</td><td class="n">{}/{}</td><td class="n">{}</td><td class="n">{}</td><td class="n">{}</td><td class="n">{}</td><td class="n">{}</td></tr>"#,
            actions(c),
            escape(&config_text(c)),
            s.pool_size,
            c.pool_capacity,
            score(s.best_score, empty),
            score(s.worst_score, empty),
            s.pool_version,
            s.episodes_completed,
            s.steps_shaped,
            eid = escape(id),
            qid = encode(id),
            key_query = escape(key_query),
        );
    }
    out.push_str("</table>");
    out
}

/// One task's fragment: its statistics and config, a legend, and its pool drawn.
pub(super) fn task_fragment(
    id: &str,
    c: &TaskConfig,
    s: &TaskStats,
    pool: &Pool,
    key_query: &str,
) -> String {
    let mut out = format!(
        r#"<p><a href="/?{}">all tasks</a></p><h1>Task <span class="task-id">{}</span></h1><p>pool version <span class="version">{}</span> · {} of {} trajectories · best {} · worst {} · {} episodes · {} steps · {} open streams</p><p class="muted">{}: {}</p>"#,
        escape(key_query.trim_start_matches('&')),
        escape(id),
        pool.version(),
        pool.len(),
        c.pool_capacity,
        score(s.best_score, s.pool_size == 0),
        score(s.worst_score, s.pool_size == 0),
        s.episodes_completed,
        s.steps_shaped,
        s.open_streams,
        actions(c),
        escape(&config_text(c)),
    );
    let n = c.action_space.num_actions();
    out.push_str(r#"<p class="legend">best first: score, length, "#);
    if n > 0 {
        out.push_str("actions");
        for (a, [r, g, b]) in PALETTE.iter().enumerate().take(n) {
            let _ = write!(
                out,
                "<span style=\"background:#{r:02x}{g:02x}{b:02x}\"></span>{a}"
            );
        }
        if n > PALETTE.len() {
            let _ = write!(out, " (action a takes colour a mod {})", PALETTE.len());
        }
    } else {
        out.push_str("each dimension's values as a line");
    }
    out.push_str("</p>");
    out.push_str(&pool_svg(pool));
    out
}

/// A page for an error: `status` and what went wrong.
pub(super) fn error_page(title: &str, message: &str) -> String {
    format!(
        r#"<!doctype html><html lang="en"><head><meta charset="utf-8"><title>{t}</title><style>{STYLE}</style></head><body><h1>{t}</h1><p>{}</p><p><a href="/">all tasks</a></p></body></html>"#,
        escape(message),
        t = escape(title),
    )
}
