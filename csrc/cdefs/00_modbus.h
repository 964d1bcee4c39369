/* The part of libmodbus 3.1.6 (modbus.h, modbus-rtu.h, modbus-tcp.h) that edgemodbus
 * uses; read by cffi only.  Float helpers are left out on purpose: Debian's patched
 * 3.1.6 get/set pairs disagree, our codec (csrc/emb_codec.c) does the conversions. */
typedef struct _modbus modbus_t;

#define MODBUS_ENOBASE 112345678
#define MODBUS_RTU_RS485 1
#define MODBUS_RTU_RTS_NONE 0
#define MODBUS_RTU_RTS_UP 1
#define MODBUS_RTU_RTS_DOWN 2
/* the protocol's limits as libmodbus has them (checked against
 * src/edgemodbus/protocol/limits.py by tests/unit/protocol/test_limits.py) */
#define MODBUS_BROADCAST_ADDRESS ...
#define MODBUS_MAX_READ_BITS ...
#define MODBUS_MAX_WRITE_BITS ...
#define MODBUS_MAX_READ_REGISTERS ...
#define MODBUS_MAX_WRITE_REGISTERS ...
#define MODBUS_MAX_WR_WRITE_REGISTERS ...
#define MODBUS_MAX_WR_READ_REGISTERS ...
#define MODBUS_MAX_PDU_LENGTH ...
#define MODBUS_RTU_MAX_ADU_LENGTH ...
#define MODBUS_TCP_MAX_ADU_LENGTH ...
#define MODBUS_TCP_SLAVE ...

modbus_t *modbus_new_rtu(const char *device, int baud, char parity, int data_bit, int stop_bit);
modbus_t *modbus_new_tcp(const char *ip_address, int port);
void modbus_free(modbus_t *ctx);

int modbus_connect(modbus_t *ctx);
void modbus_close(modbus_t *ctx);
int modbus_flush(modbus_t *ctx);
int modbus_set_socket(modbus_t *ctx, int s);
int modbus_get_socket(modbus_t *ctx);
int modbus_set_slave(modbus_t *ctx, int slave);
int modbus_set_response_timeout(modbus_t *ctx, uint32_t to_sec, uint32_t to_usec);
int modbus_set_byte_timeout(modbus_t *ctx, uint32_t to_sec, uint32_t to_usec);

int modbus_rtu_set_serial_mode(modbus_t *ctx, int mode);
int modbus_rtu_set_rts(modbus_t *ctx, int mode);
int modbus_rtu_set_rts_delay(modbus_t *ctx, int us);

int modbus_read_bits(modbus_t *ctx, int addr, int nb, uint8_t *dest);
int modbus_read_input_bits(modbus_t *ctx, int addr, int nb, uint8_t *dest);
int modbus_read_registers(modbus_t *ctx, int addr, int nb, uint16_t *dest);
int modbus_read_input_registers(modbus_t *ctx, int addr, int nb, uint16_t *dest);

int modbus_send_raw_request(modbus_t *ctx, const uint8_t *raw_req, int raw_req_length);
