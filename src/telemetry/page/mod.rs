//! The read-only dashboard (`tamrm serve --dashboard`), on the metrics listener: `/` lists
//! the caller's tasks (config, pool size, best and worst score, version, episodes,
//! steps), `/task?id=ID` draws one task's pool ([`svg`]); `/fragment/tasks` and
//! `/fragment/task?id=ID` are the same without the page around them, which the pages'
//! inline script polls. With API keys, every request needs a key of the reader role or
//! above, as an `Authorization: Bearer KEY` header or a `key` query parameter (a browser
//! cannot set the header on a link), and sees only its tenant's tasks.

mod html;
mod svg;

use std::sync::Arc;

use crate::auth::Access;
use crate::core::{Pool, TaskConfig};
use crate::error::Error;
use crate::registry::{Registry, TaskStats};
use crate::task_key::DEFAULT_TENANT;

/// The RPC whose role the dashboard needs: reading a pool (the reader role).
const READS_AS: &str = "/tamrm.v1.Shaping/GetPool";

/// What the dashboard reads: the tasks, and the API keys when the server has them.
#[derive(Clone)]
pub struct Dashboard {
    /// The server's tasks.
    pub tasks: Arc<Registry>,
    /// The key file's keys; `None`: no API keys, every task is the default tenant's.
    pub access: Option<Arc<Access>>,
}

impl std::fmt::Debug for Dashboard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dashboard").finish_non_exhaustive()
    }
}

/// An answer: status, content type, body.
pub type Answer = (http::StatusCode, &'static str, String);

const HTML: &str = "text/html; charset=utf-8";

/// The value of query parameter `name`, percent-decoded.
fn query(q: &str, name: &str) -> Option<String> {
    q.split('&').find_map(|pair| {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        (k == name).then(|| decode(v))
    })
}

fn decode(s: &str) -> String {
    let hex = |c: u8| (c as char).to_digit(16).map(|d| d as u8);
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < b.len() => match (hex(b[i + 1]), hex(b[i + 2])) {
                (Some(h), Some(l)) => {
                    out.push(h * 16 + l);
                    i += 2;
                }
                _ => out.push(b'%'),
            },
            c => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl Dashboard {
    /// The tenant whose tasks the request may see, or the error answer.
    fn tenant(&self, authorization: Option<&[u8]>, q: &str) -> Result<String, Answer> {
        let Some(access) = &self.access else {
            return Ok(DEFAULT_TENANT.to_string());
        };
        let from_query = query(q, "key").map(|k| format!("Bearer {k}"));
        let credential = authorization.or(from_query.as_deref().map(str::as_bytes));
        match access.authorize(READS_AS, credential) {
            Ok(Some(caller)) => Ok(caller.tenant().to_string()),
            Ok(None) => Ok(DEFAULT_TENANT.to_string()),
            Err(e) => {
                let (status, title) = match e {
                    Error::PermissionDenied(_) => (http::StatusCode::FORBIDDEN, "403 forbidden"),
                    _ => (http::StatusCode::UNAUTHORIZED, "401 unauthorized"),
                };
                let message = format!(
                    "{e}. The dashboard needs an API key of the reader role or above: open it as /?key=KEY, or send Authorization: Bearer KEY."
                );
                Err((status, HTML, html::error_page(title, &message)))
            }
        }
    }

    /// Answers `path?q`, or `None` when the path is not the dashboard's.
    pub async fn answer(
        &self,
        path: &str,
        q: &str,
        authorization: Option<&[u8]>,
    ) -> Option<Answer> {
        let (fragment, what) = match path {
            "/" => (false, "tasks"),
            "/task" => (false, "task"),
            "/fragment/tasks" => (true, "tasks"),
            "/fragment/task" => (true, "task"),
            _ => return None,
        };
        let tenant = match self.tenant(authorization, q) {
            Ok(t) => t,
            Err(answer) => return Some(answer),
        };
        let key_query = match query(q, "key") {
            Some(k) if self.access.is_some() => format!("&key={}", html::encode(&k)),
            _ => String::new(),
        };
        let ok = |title: &str, src: String, body: String| {
            let body = if fragment {
                body
            } else {
                html::page(title, &src, &body)
            };
            Some((http::StatusCode::OK, HTML, body))
        };
        if what == "tasks" {
            let tasks = match self.tasks.list(&tenant).await {
                Ok(t) => t,
                Err(e) => return Some(unavailable(&e)),
            };
            let rows: Vec<(String, TaskConfig, TaskStats)> = tasks
                .iter()
                .map(|t| (t.id().to_string(), *t.config(), t.stats()))
                .collect();
            return ok(
                "tamrm: tasks",
                "/fragment/tasks".into(),
                html::tasks_fragment(&rows, &key_query),
            );
        }
        let id = query(q, "id").unwrap_or_default();
        let task = match self.tasks.lookup(&tenant, &id).await {
            Ok(t) => t,
            Err(Error::TaskNotFound { .. }) | Err(Error::InvalidArgument { .. }) => {
                let message = format!("No task {id:?} here.");
                return Some((
                    http::StatusCode::NOT_FOUND,
                    HTML,
                    html::error_page("404 not found", &message),
                ));
            }
            Err(e) => return Some(unavailable(&e)),
        };
        let pool: Arc<Pool> = task.snapshot();
        let body = html::task_fragment(&id, task.config(), &task.stats(), &pool, &key_query);
        ok(
            &format!("tamrm: {id}"),
            format!("/fragment/task?id={}", html::encode(&id)),
            body,
        )
    }
}

fn unavailable(e: &Error) -> Answer {
    (
        http::StatusCode::SERVICE_UNAVAILABLE,
        HTML,
        html::error_page("503 unavailable", &e.to_string()),
    )
}

/// The page of one task's pool, as `/task?id=ID` serves it (for the benchmark).
pub fn task_page(id: &str, config: &TaskConfig, stats: &TaskStats, pool: &Pool) -> String {
    let body = html::task_fragment(id, config, stats, pool, "");
    html::page(
        id,
        &format!("/fragment/task?id={}", html::encode(id)),
        &body,
    )
}
