/*
 * Build-time configuration of the ESP32 board firmware: pin map, sample rate, output link.
 * Everything a user may need to change is here; docs/firmware.md explains each item.
 */
#ifndef FBG_BOARD_CONFIG_H
#define FBG_BOARD_CONFIG_H

/* ---- sample rate ------------------------------------------------------------------------------
 * In millihertz, so non-integer rates are exact (100000 = 100 Hz, the paper's static tests, s. 3.5).
 * Check the link budget (firmware/link_budget.py) before raising it. */
#define FBG_RATE_MHZ 100000UL

/* ---- output link ------------------------------------------------------------------------------ */
#define FBG_LINK_USB_SERIAL 1     /* UART0 through the board's USB-serial bridge */
#define FBG_LINK_BLUETOOTH_SPP 2  /* Bluetooth Classic SPP (BluetoothSerial), as in the paper (s. 4.3) */
#define FBG_LINK FBG_LINK_USB_SERIAL
#define FBG_USB_BAUD 921600UL     /* the driver's default `baud` */
#define FBG_BT_DEVICE_NAME "FBG-ACCEL"
#define FBG_FRAME_QUEUE_DEPTH 256 /* frames buffered between sampler and link writer (2.56 s at 100 Hz) */

/* ---- ADC pins (ADC1 only: ADC2 cannot be used while the radio is on) ---------------------------
 * GPIO36 = ADC1_CH0 (SENSOR_VP), GPIO39 = ADC1_CH3 (SENSOR_VN), GPIO34 = ADC1_CH6, GPIO35 = ADC1_CH7;
 * all four are input-only pins. */
#define FBG_PIN_REF 36 /* reference photodetector TIA output */
#define FBG_PIN_X 39   /* x-axis channel TIA output */
#define FBG_PIN_Y 34   /* y-axis channel TIA output */
#define FBG_PIN_Z 35   /* z-axis channel TIA output */
/* Auxiliary channel (protocol version 2, docs/protocol.md): the reference transducer of a dynamic
 * calibration (LDV velocity output or a reference accelerometer), read fifth in each sample on the
 * same clock. -1 = no aux input: the board sends version-1 frames. GPIO32 = ADC1_CH4. */
#define FBG_PIN_AUX -1

/* ---- AHT10 on I2C ------------------------------------------------------------------------------ */
#define FBG_PIN_SDA 21
#define FBG_PIN_SCL 22
#define FBG_I2C_HZ 100000UL    /* standard mode */
#define FBG_AHT_PERIOD_US 500000UL /* one reading every 0.5 s (the simulator's aht10.read_rate_hz = 2) */
#define FBG_AHT_CHECK_CRC 0    /* 1 for an AHT20/AHT21 (7-byte read with CRC-8); the AHT10 sends no CRC */

/* ---- task layout (FreeRTOS) -------------------------------------------------------------------- */
#define FBG_SAMPLER_CORE 1
#define FBG_SAMPLER_PRIORITY 20
#define FBG_WRITER_PRIORITY 5
#define FBG_AHT_PRIORITY 2

#endif
