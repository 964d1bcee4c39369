"""UI labels of the communication parameters and of the optional address item fields, as
the driver descriptor shows them (descriptor.py): label, category and control type, and
where needed the value type, options, data source and visibility (``visibleWhen``:
serial or TCP parameters).

Kept apart from the model (communication.py): :data:`LABELS` is keyed by
DriverModbusRtuParameter's field names; the descriptor lists the fields in the model's
order, with the model's defaults, limits and descriptions.
"""

from __future__ import annotations

from typing import Any

from ..datatypes import DataFormat64

BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
"""Baud rates offered by the descriptor (any 1200..921600 is accepted)."""


def _ui(
    label: str,
    category: str,
    control: str,
    *,
    type_: str | None = None,
    options: list[Any] | None = None,
    data_source: str | None = None,
    serial: bool = False,
    tcp: bool = False,
) -> dict[str, Any]:
    """The UI labels of one parameter."""
    ui: dict[str, Any] = {"label": label, "category": category, "controlType": control}
    if type_ is not None:
        ui["type"] = type_
    if options is not None:
        ui["options"] = options
    if data_source is not None:
        ui["dataSource"] = data_source
    if serial or tcp:
        ui["visibleWhen"] = {"useTcp": tcp}
    return ui


LABELS: dict[str, dict[str, Any]] = {
    "com_port": _ui(
        "串口号", "Connection", "dynamic-select", data_source="system:serial-ports", serial=True
    ),
    "baud_rate": _ui(
        "波特率", "Connection", "select", options=list(BAUD_RATES), serial=True
    ),
    "parity": _ui(
        "校验位",
        "Connection",
        "select",
        type_="int",
        options=[
            {"label": "None", "value": 0},
            {"label": "Odd", "value": 1},
            {"label": "Even", "value": 2},
        ],
        serial=True,
    ),
    "data_bits": _ui("数据位", "Connection", "select", options=[5, 6, 7, 8], serial=True),
    "stop_bits": _ui(
        "停止位",
        "Connection",
        "select",
        options=[{"label": "1", "value": 1}, {"label": "2", "value": 2}],
        serial=True,
    ),
    "slave_id": _ui("站号", "Connection", "number"),
    "use_tcp": _ui("使用TCP透传", "Connection", "switch"),
    "tcp_host": _ui("TCP主机", "Connection", "text", tcp=True),
    "tcp_port": _ui("TCP端口", "Connection", "number", tcp=True),
    "transport": _ui("传输方式", "Connection", "select"),
    "listen_host": _ui("监听地址", "Connection", "text", tcp=True),
    "listen_port": _ui("监听端口", "Connection", "number", tcp=True),
    "dtu_id": _ui("DTU注册包ID", "Connection", "text", tcp=True),
    "registration": _ui("注册包方式", "Connection", "select", tcp=True),
    "registration_pattern": _ui("注册包正则", "Connection", "text", tcp=True),
    "registration_length": _ui("注册包长度", "Connection", "number", tcp=True),
    "registration_timeout": _ui("注册超时(ms)", "Connection", "number", tcp=True),
    "heartbeat": _ui("心跳包", "Connection", "text", tcp=True),
    "heartbeat_hex": _ui("心跳包(HEX)", "Connection", "text", tcp=True),
    "registration_max_bytes": _ui("注册前最大字节数", "Connection", "number", tcp=True),
    "registration_byte_rate": _ui("注册前速率限制(字节/秒)", "Connection", "number", tcp=True),
    "max_unregistered": _ui("未注册连接上限", "Connection", "number", tcp=True),
    "max_unregistered_per_source": _ui("每来源未注册连接上限", "Connection", "number",
                                       tcp=True),
    "listen_allow_from": _ui("监听来源白名单(CIDR)", "Connection", "text", tcp=True),
    "duplicate_id": _ui("重复ID策略", "Connection", "select", tcp=True),
    "id_flip_limit": _ui("ID争用次数上限", "Connection", "number", tcp=True),
    "id_flip_window": _ui("ID争用窗口(ms)", "Connection", "number", tcp=True),
    "dtu_allow_from": _ui("DTU来源白名单(CIDR)", "Connection", "text", tcp=True),
    "registration_key": _ui("注册密钥", "Connection", "password", tcp=True),
    "engine": _ui("轮询引擎", "Connection", "select", tcp=True),
    "loop_threads": _ui("事件循环线程数", "Connection", "number", tcp=True),
    "framing": _ui("报文封装", "Connection", "select", tcp=True),
    "connect_timeout": _ui("连接超时(ms)", "Connection", "number", tcp=True),
    "reconnect_interval": _ui("重连间隔(ms)", "Connection", "number"),
    "read_timeout": _ui("读超时(ms)", "Connection", "number"),
    "byte_timeout": _ui("字节间超时(ms)", "Connection", "number"),
    "read_cycle": _ui("读取周期(ms)", "Connection", "number"),
    "rs485": _ui("RS-485 方向控制", "Connection", "select", serial=True),
    "echo": _ui("线路回显", "Connection", "switch"),
    "is_enable": _ui("启用", "Connection", "switch"),
    "data_format": _ui("数据格式", "Advanced", "select", type_="string"),
    "byte_swap16": _ui("16位值字节交换", "Advanced", "switch"),
    "data_format64": _ui(
        "64位数据格式",
        "Advanced",
        "select",
        type_="string",
        options=[{"label": "同数据格式", "value": None}]
        + [{"label": f.value, "value": f.value} for f in DataFormat64],
    ),
    "max_block_read_register_count": _ui("单块最大寄存器数", "Advanced", "number"),
    "is_block_read_require_address_continuous": _ui("块读取地址需连续", "Advanced", "switch"),
    "max_merge_address_gap": _ui("最大合并空洞", "Advanced", "number"),
    "max_block_read_bit_count": _ui("单块最大位数", "Advanced", "number"),
    "address_prefix": _ui("地址类型编号", "Advanced", "select"),
    "address_base": _ui("地址起始", "Advanced", "select"),
    "retries": _ui("重试次数", "Advanced", "number"),
    "request_interval": _ui("请求间隔(ms)", "Advanced", "number"),
    "forward_coalesce": _ui("转发读合并时效(ms)", "Advanced", "number"),
    "settle_timeout": _ui("超时后静默(ms)", "Advanced", "number"),
    "offline_after_failed_cycles": _ui("离线判定周期数", "Advanced", "number"),
    "max_backoff": _ui("最大退避(ms)", "Advanced", "number"),
    "report_mode": _ui("上报方式", "Advanced", "select"),
    "report_every": _ui("定期上报(ms)", "Advanced", "number"),
    "encoding": _ui("字符串编码", "Advanced", "text"),
    "write_single_register_function": _ui("单寄存器写功能码", "Advanced", "select"),
    "snapshot_interval": _ui("快照间隔(ms)", "Advanced", "number"),
    "alternates": _ui("备用端点", "Connection", "text"),
    "failover_after": _ui("切换前失败次数", "Connection", "number"),
    "failback_interval": _ui("主端点探测间隔(ms)", "Connection", "number"),
    "connections": _ui("并行连接数", "Connection", "number", tcp=True),
    "channel": _ui("连接通道", "Connection", "number", tcp=True),
    "flow_control": _ui("硬件流控", "Connection", "select", serial=True),
    "mqtt_host": _ui("MQTT DTU 代理地址", "Connection", "text", tcp=True),
    "mqtt_port": _ui("MQTT DTU 代理端口", "Connection", "number", tcp=True),
    "mqtt_username": _ui("MQTT 用户名", "Connection", "text", tcp=True),
    "mqtt_password": _ui("MQTT 密码", "Connection", "password", tcp=True),
    "mqtt_client_id": _ui("MQTT 客户端ID", "Connection", "text", tcp=True),
    "mqtt_keepalive": _ui("MQTT 心跳(s)", "Connection", "number", tcp=True),
    "mqtt_qos": _ui("MQTT QoS", "Connection", "select", tcp=True),
    "mqtt_tls": _ui("MQTT TLS", "Connection", "switch", tcp=True),
    "mqtt_ca_file": _ui("MQTT CA 证书", "Connection", "text", tcp=True),
    "mqtt_cert_file": _ui("MQTT 客户端证书", "Connection", "text", tcp=True),
    "mqtt_key_file": _ui("MQTT 客户端私钥", "Connection", "text", tcp=True),
    "mqtt_tls_insecure": _ui("MQTT TLS 不校验主机名", "Connection", "switch", tcp=True),
    "uplink_topic": _ui("DTU 上行主题", "Connection", "text", tcp=True),
    "downlink_topic": _ui("DTU 下行主题", "Connection", "text", tcp=True),
    "status_topic": _ui("DTU 状态主题", "Connection", "text", tcp=True),
    "online_payload": _ui("DTU 在线消息", "Connection", "text", tcp=True),
    "offline_payload": _ui("DTU 离线消息", "Connection", "text", tcp=True),
}

ITEM_LABELS: dict[str, dict[str, Any]] = {
    "read_cycle": _ui("扫描周期(ms)", "Address", "number"),
    "report_mode": _ui("上报方式", "Address", "select"),
    "report_every": _ui("定期上报(ms)", "Address", "number"),
    # engineering units (docs/engineering-units.md)
    "offset": _ui("偏移量", "Scaling", "number"),
    "raw_min": _ui("原始值下限", "Scaling", "number"),
    "raw_max": _ui("原始值上限", "Scaling", "number"),
    "eng_min": _ui("工程值下限", "Scaling", "number"),
    "eng_max": _ui("工程值上限", "Scaling", "number"),
    "clamp": _ui("超限钳位", "Scaling", "switch"),
    "scale_factor": _ui("比例因子点位(SunSpec SF)", "Scaling", "string"),
}
"""UI labels of the optional address item fields the descriptor lists
(``addressParameter``), keyed by DeviceAddressItem's field names."""
