/*
 * FBG triaxial accelerometer acquisition board: ESP32 Arduino sketch (thin hardware layer).
 *
 * All protocol logic is in the portable core (firmware/core, tested on the host by
 * test/test_firmware_core.py); this file only binds it to the ESP32:
 *   - sampler task (high priority, pinned to FBG_SAMPLER_CORE): woken by a one-shot esp_timer armed
 *     at the next read time of the drift-free scheduler; takes t_us = esp_timer_get_time() at the
 *     wake-up, reads the four ADC1 inputs back to back, builds the frame and queues it without
 *     blocking (queue full: the frame is dropped, its seq is spent, so the host counts the loss);
 *   - writer task: sends whole frames on USB serial or Bluetooth SPP; with no SPP client
 *     connected it discards them (sampling and seq go on). BOOT is put on the first frame it actually
 *     sends after power-up (fbg_link_on_send, firmware/core/fbg_board.c), not on the first sample, so
 *     the host sees a reboot even when the frames before its SPP client (re)connected were discarded;
 *   - AHT10 task (low priority): runs the non-blocking AHT10 state machine over Wire and publishes
 *     temp_cc + status bits in one 32-bit word the sampler reads atomically.
 * Configuration: fbg_board_config.h. Build: docs/firmware.md (arduino-cli with --library firmware/core).
 * NOT compiled in this repository's CI: no ESP32 toolchain is available there.
 */
#include <Arduino.h>
#include <Wire.h>

#include "esp_timer.h"
#include "fbg_board_config.h"

#if FBG_LINK == FBG_LINK_BLUETOOTH_SPP
#include "BluetoothSerial.h"
static BluetoothSerial SerialBT;
#endif

#include "fbg_aht10.h"
#include "fbg_board.h"
#include "fbg_frame.h"
#include "fbg_scheduler.h"

static fbg_board g_board;
static fbg_link g_link; /* writer task only: BOOT on the first frame delivered after power-up */
static fbg_scheduler g_sched;
static fbg_aht10 g_aht;
static esp_timer_handle_t g_sample_timer;
static TaskHandle_t g_sampler_task;
static QueueHandle_t g_frames;
static volatile uint32_t g_temp_word;      /* (status bits << 16) | (uint16_t)temp_cc, written by the AHT10 task */
static volatile uint32_t g_frames_dropped; /* queue full */
static volatile uint32_t g_frames_unsent;  /* no SPP client */

/* ---- I2C access for the AHT10 state machine (0 = ACK, non-zero = NACK / bus error) ------------ */
static int wire_write(void *ctx, uint8_t addr, const uint8_t *data, size_t n)
{
    (void)ctx;
    Wire.beginTransmission(addr);
    Wire.write(data, n);
    return Wire.endTransmission() == 0 ? 0 : 1;
}

static int wire_read(void *ctx, uint8_t addr, uint8_t *data, size_t n)
{
    (void)ctx;
    size_t got = Wire.requestFrom((uint16_t)addr, (size_t)n);
    if (got != n) {
        return 1;
    }
    for (size_t i = 0; i < n; i++) {
        data[i] = (uint8_t)Wire.read();
    }
    return 0;
}

static void aht_task(void *arg)
{
    (void)arg;
    const fbg_i2c_bus bus = {wire_write, wire_read, NULL};
    for (;;) {
        uint64_t now = (uint64_t)esp_timer_get_time();
        uint64_t wake = fbg_aht10_poll(&g_aht, &bus, now);
        g_temp_word = ((uint32_t)fbg_aht10_status_bits(&g_aht) << 16) | (uint16_t)fbg_aht10_temp_cc(&g_aht);
        if (wake == UINT64_MAX) { /* sensor absent: nothing more to do until the next boot */
            vTaskDelete(NULL);
        }
        uint64_t after = (uint64_t)esp_timer_get_time();
        uint32_t wait_ms = wake > after ? (uint32_t)((wake - after + 999u) / 1000u) : 0u;
        vTaskDelay(pdMS_TO_TICKS(wait_ms) > 0 ? pdMS_TO_TICKS(wait_ms) : 1);
    }
}

/* ---- sampling ----------------------------------------------------------------------------------- */
static void on_sample_timer(void *arg)
{
    (void)arg;
    xTaskNotifyGive(g_sampler_task); /* esp_timer callbacks run in the esp_timer task, not in an ISR */
}

static void arm_next_read(void)
{
    int64_t delay = (int64_t)fbg_sched_next_us(&g_sched) - esp_timer_get_time();
    if (delay < 20) { /* due now (catching up) or too close for a one-shot timer: go again at once */
        xTaskNotifyGive(g_sampler_task);
    } else {
        esp_timer_start_once(g_sample_timer, (uint64_t)delay);
    }
}

#if FBG_PIN_AUX >= 0
#define FBG_FRAME_SIZE FBG_FRAME_SIZE_V2 /* version 2: aux appended (docs/protocol.md) */
#else
#define FBG_FRAME_SIZE FBG_FRAME_SIZE_V1
#endif

static void sampler_task(void *arg)
{
    (void)arg;
    arm_next_read();
    for (;;) {
        ulTaskNotifyTake(pdTRUE, portMAX_DELAY);
        uint64_t t_us = (uint64_t)esp_timer_get_time(); /* the sample instant: at the trigger */
        uint16_t adc[4];
        adc[0] = (uint16_t)analogRead(FBG_PIN_REF);
        adc[1] = (uint16_t)analogRead(FBG_PIN_X);
        adc[2] = (uint16_t)analogRead(FBG_PIN_Y);
        adc[3] = (uint16_t)analogRead(FBG_PIN_Z);
#if FBG_PIN_AUX >= 0
        uint16_t aux = (uint16_t)analogRead(FBG_PIN_AUX); /* fifth conversion: its skew is board.adc_channel_skew_us */
#endif
        uint32_t skipped = 0;
        int late = fbg_sched_take(&g_sched, t_us, &skipped);
        uint32_t tw = g_temp_word;
        fbg_sample s;
        fbg_board_next_sample(&g_board, t_us, adc, (int16_t)(uint16_t)(tw & 0xFFFFu), (uint8_t)(tw >> 16), late, &s);
        fbg_board_skip(&g_board, skipped);
        uint8_t frame[FBG_FRAME_SIZE];
#if FBG_PIN_AUX >= 0
        fbg_frame_encode_v2(&s, aux, frame);
#else
        fbg_frame_encode_v1(&s, frame);
#endif
        if (xQueueSend(g_frames, frame, 0) != pdTRUE) {
            g_frames_dropped++;
        }
        arm_next_read();
    }
}

/* ---- output link -------------------------------------------------------------------------------- */
static void writer_task(void *arg)
{
    (void)arg;
    uint8_t frame[FBG_FRAME_SIZE];
    for (;;) {
        if (xQueueReceive(g_frames, frame, portMAX_DELAY) != pdTRUE) {
            continue;
        }
#if FBG_LINK == FBG_LINK_BLUETOOTH_SPP
        if (!SerialBT.hasClient()) {
            g_frames_unsent++; /* link lost: discard, keep sampling; the host sees a seq gap */
            continue;          /* (a discarded frame never takes the BOOT bit: see below) */
        }
        int boot = fbg_link_on_send(&g_link, frame, sizeof frame); /* BOOT + CRC on the first frame sent */
        if (SerialBT.write(frame, sizeof frame) != sizeof frame && boot == 1) {
            fbg_link_init(&g_link); /* the BOOT frame did not go out whole: the next frame sent carries BOOT */
        }
#else
        fbg_link_on_send(&g_link, frame, sizeof frame); /* same contract on USB (there the first sample) */
        Serial.write(frame, sizeof frame);
#endif
    }
}

void setup()
{
#if FBG_LINK == FBG_LINK_BLUETOOTH_SPP
    SerialBT.begin(FBG_BT_DEVICE_NAME); /* SPP slave; the host binds /dev/rfcomm0 to it */
#else
    Serial.setTxBufferSize(4096); /* > 100 frames of TX buffer before begin() */
    Serial.begin(FBG_USB_BAUD);
#endif
    analogReadResolution(12);
    analogSetAttenuation(ADC_11db); /* about 0..3.1 V full scale on ADC1 */
    Wire.begin(FBG_PIN_SDA, FBG_PIN_SCL, FBG_I2C_HZ);

    fbg_board_init(&g_board);
    fbg_link_init(&g_link); /* before the writer task starts */
    fbg_aht10_config acfg = fbg_aht10_default_config();
    acfg.period_us = FBG_AHT_PERIOD_US;
    acfg.check_crc = FBG_AHT_CHECK_CRC;
    uint64_t now = (uint64_t)esp_timer_get_time();
    fbg_aht10_init(&g_aht, &acfg, now);
    g_temp_word = 0;
    /* First read one period after start-up, on the board clock (us since boot). */
    fbg_sched_init(&g_sched, FBG_RATE_MHZ, now + 1000000000ull / FBG_RATE_MHZ);

    g_frames = xQueueCreate(FBG_FRAME_QUEUE_DEPTH, FBG_FRAME_SIZE);
    const esp_timer_create_args_t targs = {on_sample_timer, NULL, ESP_TIMER_TASK, "fbg_sample", false};
    esp_timer_create(&targs, &g_sample_timer);
    xTaskCreatePinnedToCore(writer_task, "fbg_writer", 4096, NULL, FBG_WRITER_PRIORITY, NULL, 1 - FBG_SAMPLER_CORE);
    xTaskCreatePinnedToCore(aht_task, "fbg_aht10", 4096, NULL, FBG_AHT_PRIORITY, NULL, 1 - FBG_SAMPLER_CORE);
    xTaskCreatePinnedToCore(sampler_task, "fbg_sampler", 4096, NULL, FBG_SAMPLER_PRIORITY, &g_sampler_task,
                            FBG_SAMPLER_CORE);
}

void loop()
{
    vTaskDelay(pdMS_TO_TICKS(1000)); /* all work is in the tasks */
}
