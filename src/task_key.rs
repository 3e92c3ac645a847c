//! The key of a tenant's task in the registry and the store (SPEC §11): the one place
//! that knows its format. A leaf module: it uses nothing of the crate, so the error type,
//! the registry, the stores and the auth layer can all use it.

/// The tenant of callers without credentials (a server without `--api-keys`, the
/// embedded engine), and the owner of data written before tenants existed.
pub const DEFAULT_TENANT: &str = "default";

/// Separates tenant and task id in a [`task_key`]; a task id cannot contain it.
const TENANT_SEPARATOR: char = '@';

/// The key of tenant `tenant`'s task `id` in the registry and the store: the id itself
/// for [`DEFAULT_TENANT`] (so data written before tenants existed is the default
/// tenant's), `tenant@id` for any other. Task ids never contain `@`
/// (`session::validate_task_id`), tenant names neither (`auth`), so the key is unambiguous.
pub fn task_key(tenant: &str, id: &str) -> String {
    if tenant == DEFAULT_TENANT {
        id.to_string()
    } else {
        format!("{tenant}{TENANT_SEPARATOR}{id}")
    }
}

/// The (tenant, id) of a [`task_key`].
pub fn split_key(key: &str) -> (&str, &str) {
    key.split_once(TENANT_SEPARATOR)
        .unwrap_or((DEFAULT_TENANT, key))
}

#[cfg(test)]
mod tests;
