//! AimRT's RPC status codes: every module RPC call ends with exactly one.

/// The outcome of an RPC call, with AimRT's numeric codes (`aimrt_rpc_status_code_t`) and
/// texts. Displays as AimRT's `Status::ToString()`.
///
/// ```
/// use aimrt_plugin_api::RpcStatus;
/// assert_eq!(RpcStatus::OK.to_string(), "suc, code 0, msg: OK");
/// assert_eq!(RpcStatus::UNKNOWN.to_string(), "fail, code 1, msg: Unknown error");
/// assert_eq!(RpcStatus::from_code(4242).to_string(), "fail, code 4242, msg: Unknown code");
/// assert!(RpcStatus::TIMEOUT.is_timeout() && !RpcStatus::TIMEOUT.is_ok());
/// ```
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct RpcStatus(u32);

macro_rules! codes {
    ($($name:ident = $code:literal, $text:literal;)*) => {
        impl RpcStatus {
            $(
                #[doc = concat!("`", stringify!($code), "`: ", $text, ".")]
                pub const $name: RpcStatus = RpcStatus($code);
            )*

            /// AimRT's name of the code (`"SVR_NOT_FOUND"`), or `None` for a code AimRT
            /// does not define.
            pub const fn name(self) -> Option<&'static str> {
                match self.0 {
                    $($code => Some(stringify!($name)),)*
                    _ => None,
                }
            }

            /// AimRT's text for the code (`"Server not found"`); `"Unknown code"` for a code
            /// AimRT does not define.
            pub const fn text(self) -> &'static str {
                match self.0 {
                    $($code => $text,)*
                    _ => "Unknown code",
                }
            }
        }
    };
}

codes! {
    OK = 0, "OK";
    UNKNOWN = 1, "Unknown error";
    TIMEOUT = 2, "Timeout";
    SVR_UNKNOWN = 1000, "Server side unknown error";
    SVR_BACKEND_INTERNAL_ERROR = 1001, "Server side backend internal error";
    SVR_NOT_IMPLEMENTED = 1002, "Server not implemented";
    SVR_NOT_FOUND = 1003, "Server not found";
    SVR_INVALID_SERIALIZATION_TYPE = 1004, "Server side invalid serialization type";
    SVR_SERIALIZATION_FAILED = 1005, "Server side serialization failed";
    SVR_INVALID_DESERIALIZATION_TYPE = 1006, "Server side invalid deserialization type";
    SVR_DESERIALIZATION_FAILED = 1007, "Server side deserialization failed";
    SVR_HANDLE_FAILED = 1008, "Server handle failed";
    SVR_NOT_READY = 1009, "Server not ready";
    CLI_UNKNOWN = 2000, "Client side unknown error";
    CLI_FUNC_NOT_REGISTERED = 2001, "Client side function not registered";
    CLI_BACKEND_INTERNAL_ERROR = 2002, "Client side backend internal error";
    CLI_INVALID_CONTEXT = 2003, "Client side invalid context";
    CLI_INVALID_ADDR = 2004, "Client side invalid address";
    CLI_INVALID_SERIALIZATION_TYPE = 2005, "Client side invalid serialization type";
    CLI_SERIALIZATION_FAILED = 2006, "Client side serialization failed";
    CLI_INVALID_DESERIALIZATION_TYPE = 2007, "Client side invalid deserialization type";
    CLI_DESERIALIZATION_FAILED = 2008, "Client side deserialization failed";
    CLI_NO_BACKEND_TO_HANDLE = 2009, "Client side no backend to handle";
    CLI_SEND_REQ_FAILED = 2010, "Client side send req failed";
    CLI_NOT_READY = 2011, "Client side not ready";
}

impl RpcStatus {
    /// The status with `code`, known to AimRT or not (a backend passes codes through).
    pub const fn from_code(code: u32) -> RpcStatus {
        RpcStatus(code)
    }

    /// The numeric code, as it travels on the wire.
    pub const fn code(self) -> u32 {
        self.0
    }

    /// Whether the call succeeded (code 0).
    pub const fn is_ok(self) -> bool {
        self.0 == 0
    }

    /// Whether the call's deadline passed (code 2, on every backend).
    pub const fn is_timeout(self) -> bool {
        self.0 == RpcStatus::TIMEOUT.0
    }

    /// Whether the server side produced the status (codes 1000 ..= 1999).
    pub const fn is_server_side(self) -> bool {
        self.0 >= 1000 && self.0 < 2000
    }

    /// Whether the client side produced the status (codes 2000 ..= 2999).
    pub const fn is_client_side(self) -> bool {
        self.0 >= 2000 && self.0 < 3000
    }
}

impl Default for RpcStatus {
    fn default() -> Self {
        RpcStatus::OK
    }
}

impl From<u32> for RpcStatus {
    fn from(code: u32) -> Self {
        RpcStatus(code)
    }
}

impl From<RpcStatus> for u32 {
    fn from(status: RpcStatus) -> Self {
        status.0
    }
}

/// `suc, code 0, msg: OK` / `fail, code 1003, msg: Server not found`, as AimRT.
impl std::fmt::Display for RpcStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let outcome = if self.is_ok() { "suc" } else { "fail" };
        write!(f, "{outcome}, code {}, msg: {}", self.0, self.text())
    }
}

impl std::fmt::Debug for RpcStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.name() {
            Some(name) => write!(f, "RpcStatus::{name}"),
            None => write!(f, "RpcStatus({})", self.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_has_aimrts_number_name_and_text() {
        let table = [
            (RpcStatus::OK, 0, "OK", "OK"),
            (RpcStatus::TIMEOUT, 2, "TIMEOUT", "Timeout"),
            (
                RpcStatus::SVR_NOT_IMPLEMENTED,
                1002,
                "SVR_NOT_IMPLEMENTED",
                "Server not implemented",
            ),
            (
                RpcStatus::SVR_NOT_FOUND,
                1003,
                "SVR_NOT_FOUND",
                "Server not found",
            ),
            (
                RpcStatus::SVR_HANDLE_FAILED,
                1008,
                "SVR_HANDLE_FAILED",
                "Server handle failed",
            ),
            (
                RpcStatus::SVR_NOT_READY,
                1009,
                "SVR_NOT_READY",
                "Server not ready",
            ),
            (
                RpcStatus::CLI_INVALID_CONTEXT,
                2003,
                "CLI_INVALID_CONTEXT",
                "Client side invalid context",
            ),
            (
                RpcStatus::CLI_NO_BACKEND_TO_HANDLE,
                2009,
                "CLI_NO_BACKEND_TO_HANDLE",
                "Client side no backend to handle",
            ),
            (
                RpcStatus::CLI_NOT_READY,
                2011,
                "CLI_NOT_READY",
                "Client side not ready",
            ),
        ];
        for (status, code, name, text) in table {
            assert_eq!(status.code(), code);
            assert_eq!(status.name(), Some(name));
            assert_eq!(status.text(), text);
            assert_eq!(RpcStatus::from_code(code), status);
        }
        let defined = (0..3000).filter(|&c| RpcStatus(c).name().is_some()).count();
        assert_eq!(defined, 3 + 10 + 12, "AimRT defines 25 codes");
    }

    #[test]
    fn sides_and_display() {
        assert!(
            RpcStatus::SVR_UNKNOWN.is_server_side() && !RpcStatus::SVR_UNKNOWN.is_client_side()
        );
        assert!(
            RpcStatus::CLI_UNKNOWN.is_client_side() && !RpcStatus::CLI_UNKNOWN.is_server_side()
        );
        assert_eq!(
            RpcStatus::SVR_NOT_FOUND.to_string(),
            "fail, code 1003, msg: Server not found"
        );
        assert_eq!(format!("{:?}", RpcStatus::TIMEOUT), "RpcStatus::TIMEOUT");
        assert_eq!(format!("{:?}", RpcStatus(7)), "RpcStatus(7)");
        assert_eq!(RpcStatus::default(), RpcStatus::OK);
    }
}
