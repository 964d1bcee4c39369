"""TLS to an MQTT broker, shared by the northbound's ``mqtt.tls`` section
(northbound/mqtt/settings.py) and the mqtt-dtu keys (config/mqtt_dtu.py): the checks of
the CA, certificate and key files before anything connects (:func:`tls_file_problems`)
and the words for a connect that failed (:func:`connect_error_text`).

Each caller names its own keys (``caFile`` or ``mqttCaFile``...), so a problem names
the field as the user wrote it.
"""

from __future__ import annotations

import os
import socket
import ssl
from collections.abc import Callable
from typing import Any

from .files import path_kind
from .problems import Problem


def not_a_file(path: str) -> str | None:
    """Why an existing ``path`` is no regular file (a FIFO would block the load, a
    device or socket is no file to keep), or None (a regular file, or nothing there)."""
    kind = path_kind(path)
    if kind is None:
        return None
    return "is a directory, not a file" if kind == "a directory" else \
        f"is {kind}, not a regular file"


def _file_problem(path: str) -> str | None:
    """Why ``path`` cannot be read as a file by this process, or None."""
    kind = not_a_file(path)
    if kind is not None:
        return kind
    try:
        with open(path, "rb") as file:
            file.read(1)
    except FileNotFoundError:
        return "no such file"
    except IsADirectoryError:
        return "is a directory, not a file"
    except PermissionError:
        return f"not readable by this process (uid {os.geteuid()}): permission denied"
    except OSError as exc:
        return f"cannot be read: {exc.strerror or exc}"
    return None


def _no_password() -> bytes:
    raise ValueError("the key is encrypted; give an unencrypted key file")


def _pem_problems(field: str, path: str, label: str, what: str,
                  hint: str = "") -> list[Problem]:
    """[] if the file holds a PEM block ``-----BEGIN ...{label}-----``."""
    with open(path, "rb") as file:
        text = file.read(1 << 20)
    if f"{label}-----".encode() in text and b"-----BEGIN " in text:
        return []
    return [Problem(field, path, f"no PEM {what} in it{hint}")]


_SSL_REASONS = {
    "NO_CERTIFICATE_OR_CRL_FOUND": "no PEM certificate in it",
    "KEY_VALUES_MISMATCH": "the key does not belong to the certificate",
}


def _ssl_problem(load: Callable[..., object], *args: Any, **kwargs: Any) -> str | None:
    """Why OpenSSL refuses the files ``load(*args, **kwargs)`` reads (not PEM, key and
    certificate do not match...), or None."""
    try:
        load(*args, **kwargs)
    except ssl.SSLError as exc:
        reason = str(exc.reason or exc)
        return _SSL_REASONS.get(reason, f"not usable for TLS: {reason}")
    except (ValueError, OSError) as exc:
        return f"not usable for TLS: {exc}"
    return None


def tls_file_problems(ca_file: str | None, cert_file: str | None, key_file: str | None,
                      *, where: str = "", keys: tuple[str, str, str] = (
                          "caFile", "certFile", "keyFile")) -> list[Problem]:
    """What is wrong with the TLS files that are set (None: not set): missing,
    unreadable, a FIFO or directory, not PEM, a key without its certificate or not its
    key; each problem names ``where`` + its key of ``keys`` (CA, certificate, key).
    [] when TLS can be set up from them."""
    ca_key, cert_key, key_key = keys
    found: list[Problem] = []
    for key, path in ((ca_key, ca_file), (cert_key, cert_file), (key_key, key_file)):
        if path is None:
            continue
        message = _file_problem(path)
        if message is None and key == ca_key:
            message = _ssl_problem(ssl.create_default_context, cafile=path)
        if message is not None:
            found.append(Problem(f"{where}{key}", path, message))
    if key_file is not None and cert_file is None:
        found.append(Problem(f"{where}{key_key}", key_file,
                             f"needs {cert_key} (the client certificate of this key)"))
    if not found and cert_file is not None:
        found += _pem_problems(f"{where}{cert_key}", cert_file, "CERTIFICATE",
                               "certificate")
        key_field, key_path = ((key_key, key_file) if key_file is not None else
                               (cert_key, cert_file))  # no key file: the key is in it
        found += _pem_problems(f"{where}{key_field}", key_path, "PRIVATE KEY",
                               "private key", "" if key_file is not None else
                               f" ({key_key} is not set, so the key must be in {cert_key})")
    if not found and cert_file is not None:
        chain = ssl.create_default_context().load_cert_chain
        problem = _ssl_problem(chain, cert_file, key_file, password=_no_password)
        if problem is not None:
            found.append(Problem(f"{where}{cert_key}/{key_key}", f"{cert_file}, {key_file}",
                                 problem))
    return found


def connect_error_text(exc: BaseException, tls: str | None,
                       timeout: str = "connectTimeout") -> str:
    """A connect error in words: ``connection refused``, ``timed out`` (``timeout``
    says which), the TLS error; with ``tls`` (the key that turned TLS on, e.g.
    ``mqtt.tls``), a handshake cut short hints at a port that does not speak TLS."""
    if tls and isinstance(exc, (ConnectionResetError, BrokenPipeError, ssl.SSLError)) and (
            not isinstance(exc, ssl.CertificateError)):
        return (f"{connect_error_text(exc, None, timeout)} ({tls} is on: does this port "
                "speak TLS?)")
    if isinstance(exc, ssl.SSLCertVerificationError):
        return f"TLS certificate check failed: {exc.verify_message or exc}"
    if isinstance(exc, ssl.CertificateError):  # paho's own host name check
        return f"TLS certificate check failed: {exc}"
    if isinstance(exc, ssl.SSLError):
        return f"TLS handshake failed: {exc.reason or exc}"
    if isinstance(exc, socket.gaierror):
        return f"cannot resolve the host name: {exc.strerror or exc}"
    if isinstance(exc, TimeoutError) and not exc.strerror:
        return f"timed out ({timeout})"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower() if exc.strerror[:1].isupper() else exc.strerror
    return str(exc) or type(exc).__name__


__all__ = ["connect_error_text", "not_a_file", "tls_file_problems"]
